//! `nak eval`: DCM of a model on a dataset split, per subset, on screen and as JSON (with each
//! scored sample's errors), and the time the serving engine takes per request, measured one request
//! at a time after the scoring pass.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use nak::data::dataset;
use nak::data::dcm::{self, SampleError, Summary};
use nak::data::force_error::{self, ForceSummary, GraspForceError};
use nak::engine::{Engine, Forces, HELD_NODES, Request, VOLUMETRIC_LAW_KEY};
use rayon::prelude::*;

#[derive(clap::Args)]
pub struct EvalArgs {
    /// A dataset made by `nak datagen`.
    #[arg(long)]
    pub data: PathBuf,
    /// Model to evaluate.
    #[arg(long, default_value = "kelvinlet")]
    pub model: String,
    /// Which samples: train, val, test or all.
    #[arg(long, default_value = "test")]
    split: String,
    /// Write the results as JSON here: per subset, and each scored sample's errors (and `held_nodes`:
    /// how the served field answers the nodes a grasp holds, docs/design.md §7).
    #[arg(long)]
    output: Option<PathBuf>,
    /// Requests of the split (spread evenly over it) timed one at a time after scoring (0: no timing).
    #[arg(long, default_value_t = 200)]
    latency_samples: usize,
}

/// One scored sample in the JSON report, so that where a model misses can be looked up by grasp.
#[derive(serde::Serialize)]
struct ScoredSample {
    index: u64,
    subset: String,
    #[serde(flatten)]
    error: SampleError,
}

/// Per-stage engine time of requests run one at a time (no other request competing for the cores).
#[derive(serde::Serialize)]
struct Latency {
    requests: usize,
    total: Percentiles,
    prior: Percentiles,
    network: Percentiles,
}

#[derive(serde::Serialize)]
struct Percentiles {
    p50: f64,
    p90: f64,
    p99: f64,
}

impl Percentiles {
    fn of(mut values: Vec<f64>) -> Self {
        values.sort_by(f64::total_cmp);
        let at = |q: f64| values[((values.len() - 1) as f64 * q).round() as usize];
        Percentiles {
            p50: at(0.5),
            p90: at(0.9),
            p99: at(0.99),
        }
    }
}

/// Times `requests` through the engine one at a time, after a few untimed warm-up requests.
fn time_requests(engine: &Engine, requests: &[Request]) -> Result<Option<Latency>, nak::engine::EngineError> {
    if requests.is_empty() {
        return Ok(None);
    }
    for request in requests.iter().cycle().take(10) {
        engine.predict(request)?;
    }
    let (mut total, mut prior, mut network) = (Vec::new(), Vec::new(), Vec::new());
    for request in requests {
        let t = engine.predict(request)?.timing;
        total.push(f64::from(t.total_us));
        prior.push(f64::from(t.prior_us));
        network.push(f64::from(t.network_us));
    }
    Ok(Some(Latency {
        requests: requests.len(),
        total: Percentiles::of(total),
        prior: Percentiles::of(prior),
        network: Percentiles::of(network),
    }))
}

/// The grasp force table, or why there is none.
fn print_forces(forces: &BTreeMap<String, ForceSummary>, engine: &Engine, model: &str) {
    if forces.is_empty() {
        let gives = engine
            .models()
            .find(|m| m.name == model)
            .is_some_and(|m| m.forces != Forces::Unavailable);
        if gives {
            println!("  grasp forces: the dataset stores none (made before nak stored them: regenerate it)");
        } else {
            println!("  grasp forces: {model} gives none");
        }
        return;
    }
    println!("  grasp forces against the finite elements (per grasp: |F̂ − F| / |F|, |F̂| / |F|, angle):");
    println!("  subset       grasps   mean rel err   median rel err   median |F̂|/|F|   median angle °");
    for subset in ["single", "multi", "combined"] {
        if let Some(s) = forces.get(subset) {
            println!(
                "  {:<10} {:>8}  {:>13.3}  {:>15.3}  {:>15.3}  {:>15.1}",
                subset,
                s.grasps,
                s.mean_relative_error,
                s.median_relative_error,
                s.median_magnitude_ratio,
                s.median_angle_deg
            );
        }
    }
}

/// The dataset at `dir`, refused unless it was made on the engine's mesh.
pub fn dataset_for(dir: &Path, engine: &Engine) -> anyhow::Result<dataset::DatasetInfo> {
    let info = dataset::read_info(dir)?;
    let mesh = engine.mesh();
    if info.mesh_hash != mesh.content_hash {
        bail!(
            "{} was made on mesh {} ({}); pass that mesh with --mesh (the loaded one is {})",
            dir.display(),
            info.mesh_name,
            info.mesh_hash,
            mesh.content_hash
        );
    }
    Ok(info)
}

/// Refuses to score `model` on nonlinear data solved under another hyperelastic law than the
/// model's answers (a network's training data, green-tangent's preload) or the mesh's model.toml.
fn check_law(info: &dataset::DatasetInfo, data: &Path, engine: &Engine, model: &str) -> anyhow::Result<()> {
    let Some(law) = info.volumetric_law else {
        return Ok(());
    };
    let configured = engine.mesh().config.volumetric_law;
    if configured != law {
        bail!(
            "{} was solved under the volumetric law {law}, but the mesh's model.toml sets {configured}: \
             fields of two laws are not compared (set [hyperelastic] volumetric_law to match, or remake the data)",
            data.display()
        );
    }
    let model_law = engine
        .models()
        .find(|m| m.name == model)
        .and_then(|m| m.metadata.get(VOLUMETRIC_LAW_KEY));
    if let Some(model_law) = model_law
        && model_law != law.name()
    {
        bail!(
            "model {model} was made under the volumetric law {model_law}, but {} was solved under {law}: \
             retrain the model on data of this law",
            data.display()
        );
    }
    Ok(())
}

pub fn run(args: &EvalArgs, engine: &Engine) -> anyhow::Result<()> {
    let info = dataset_for(&args.data, engine)?;
    check_law(&info, &args.data, engine, &args.model)?;
    let mesh = engine.mesh();
    let mut force_errors: BTreeMap<String, Vec<GraspForceError>> = BTreeMap::new();
    let mut failed = Vec::new();
    let mut per_sample: Vec<ScoredSample> = Vec::new();
    let mut timed: Vec<Request> = Vec::new();
    let in_split = |s: &dataset::SampleRecord| args.split == "all" || s.split == args.split;
    // Long nonlinear runs are scored while they are still being generated: complete chunks only.
    let complete = dataset::complete_chunks(&args.data, info.chunks());
    let incomplete = complete.iter().filter(|&&c| !c).count();
    for chunk in (0..info.chunks()).filter(|&c| complete[c]) {
        let samples =
            dataset::read_chunk(&args.data, chunk, info.node_count).with_context(|| format!("chunk {chunk}"))?;
        let request_of = |sample: &dataset::SampleRecord| Request {
            model: args.model.clone(),
            grasps: sample.grasps(),
            ..Request::default()
        };
        timed.extend(
            samples
                .iter()
                .filter(|(s, _)| in_split(s) && !s.failed())
                .map(|(s, _)| request_of(s)),
        );
        let scored: Vec<(&dataset::SampleRecord, SampleError, Vec<GraspForceError>)> = samples
            .par_iter()
            .filter(|(s, _)| in_split(s) && !s.failed())
            .map(|(sample, truth)| {
                let prediction = engine.predict(&request_of(sample))?;
                let forces = match (sample.forces(), &prediction.grasp_forces) {
                    (Some(truth), Some(served)) => truth
                        .iter()
                        .zip(served)
                        .filter_map(|(t, s)| force_error::grasp_force_error(t, s))
                        .collect(),
                    _ => Vec::new(),
                };
                Ok((
                    sample,
                    dcm::sample_error(truth, &prediction.displacements, &mesh.nodal_volumes),
                    forces,
                ))
            })
            .collect::<Result<_, nak::engine::EngineError>>()?;
        failed.extend(
            samples
                .iter()
                .filter(|(s, _)| in_split(s) && s.failed())
                .map(|(s, _)| s.index),
        );
        for (sample, e, f) in scored {
            for key in ["combined", sample.subset.as_str()] {
                force_errors.entry(key.to_owned()).or_default().extend(&f);
            }
            per_sample.push(ScoredSample {
                index: sample.index,
                subset: sample.subset.clone(),
                error: e,
            });
        }
    }
    let mut subsets: BTreeSet<&str> = per_sample.iter().map(|s| s.subset.as_str()).collect();
    subsets.insert("combined");
    let results: BTreeMap<String, Summary> = subsets
        .into_iter()
        .filter_map(|subset| {
            let errors: Vec<SampleError> = per_sample
                .iter()
                .filter(|s| subset == "combined" || s.subset == subset)
                .map(|s| s.error)
                .collect();
            dcm::summarize(&errors).map(|s| (subset.to_owned(), s))
        })
        .collect();
    if results.is_empty() {
        bail!("no samples in split {:?} of {}", args.split, args.data.display());
    }
    println!(
        "{} on {} ({} regime, split {}):",
        args.model,
        args.data.display(),
        info.regime,
        args.split
    );
    if let Some(shard) = info.shard {
        println!(
            "  shard {shard} of the dataset: its {} complete chunks only (nak dataset join assembles the whole)",
            info.chunks() - incomplete
        );
    } else if incomplete > 0 {
        println!(
            "  {incomplete} of {} chunks are not generated yet and were left out (nak datagen resumes them)",
            info.chunks()
        );
    }
    if !failed.is_empty() {
        println!(
            "  {} samples left out: their ground-truth solve failed (indices {failed:?}; see their chunk JSON)",
            failed.len()
        );
    }
    println!("  subset      samples   DCM %   ± s.e.   DCM nodal %   DCM code %   mean err   median err   max err");
    for subset in ["single", "multi", "combined"] {
        if let Some(s) = results.get(subset) {
            let error = s.dcm_standard_error.map_or("–".to_owned(), |e| format!("{e:.2}"));
            println!(
                "  {:<10} {:>8}  {:>6.2}  {:>7}  {:>12.2}  {:>11.2}  {:>9.4}  {:>11.4}  {:>8.4}",
                subset, s.samples, s.dcm, error, s.dcm_nodal, s.dcm_code, s.mean_error, s.median_error, s.max_error
            );
        }
    }
    println!(
        "  (DCM: volume-weighted, docs/design.md §6, with its standard error over the samples; code: the \
         paper's code form, comparable with its tables)"
    );
    let forces: BTreeMap<String, ForceSummary> = force_errors
        .iter()
        .filter_map(|(k, v)| force_error::summarize(v).map(|s| (k.clone(), s)))
        .collect();
    print_forces(&forces, engine, &args.model);
    // Time a sample spread evenly over the split: single- and two-grasper requests in proportion.
    let stride = timed.len().div_ceil(args.latency_samples.max(1)).max(1);
    let timed: Vec<Request> = if args.latency_samples == 0 {
        Vec::new()
    } else {
        timed.into_iter().step_by(stride).collect()
    };
    let latency = time_requests(engine, &timed)?;
    if let Some(l) = &latency {
        println!(
            "  engine time per request, {} requests one at a time: total p50 {:.3} ms (p90 {:.3}), \
             prior p50 {:.3} ms, network p50 {:.3} ms",
            l.requests,
            l.total.p50 / 1e3,
            l.total.p90 / 1e3,
            l.prior.p50 / 1e3,
            l.network.p50 / 1e3
        );
    }
    if let Some(path) = &args.output {
        let json = serde_json::json!({
            "model": args.model, "data": args.data, "split": args.split, "seed": info.seed, "regime": info.regime,
            "mesh_hash": info.mesh_hash, "subsets": results, "grasp_forces": forces,
            "failed_samples": failed, "samples": per_sample,
            "latency_us": latency, "threads": rayon::current_num_threads(), "held_nodes": HELD_NODES,
        });
        std::fs::write(path, serde_json::to_string_pretty(&json)? + "\n")
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(())
}
