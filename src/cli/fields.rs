//! `nak dataset fields`: a served model's field for every sample of a dataset split, as one tensor
//! file. Training uses it for priors it cannot compute itself (green-linear's Green's functions live
//! in nak), so that a network learns its residual against exactly the field nak serves.

use std::path::PathBuf;

use anyhow::Context;
use nak::data::dataset;
use nak::engine::{Engine, Request};
use rayon::prelude::*;
use safetensors::tensor::{Dtype, TensorView};

#[derive(clap::Args)]
pub struct FieldsArgs {
    /// A dataset made by `nak datagen`.
    #[arg(long)]
    pub data: PathBuf,
    /// The served model whose field is written.
    #[arg(long)]
    pub model: String,
    /// Which samples: train, val, test or all.
    #[arg(long, default_value = "train")]
    split: String,
    /// The file to write: `displacement` f32 [S, N, 3] and `index` i64 [S] (the samples' dataset
    /// indices, in dataset order; failed and not yet generated samples are left out), and for a model
    /// that gives forces `grasp_forces` f32 [S, G, 3] (each grasp's force, N; zero past a sample's
    /// own grasps).
    #[arg(long)]
    out: PathBuf,
}

/// One sample's served field, and its grasp forces when the model gives them.
type Served = (Vec<f32>, Option<Vec<[f64; 3]>>);

pub fn run(args: &FieldsArgs, engine: &Engine) -> anyhow::Result<()> {
    if !matches!(args.split.as_str(), "train" | "val" | "test" | "all") {
        anyhow::bail!("--split {:?}: expected train, val, test or all", args.split);
    }
    let info = super::eval::dataset_for(&args.data, engine)?;
    let complete = dataset::complete_chunks(&args.data, info.chunks());
    let bar = indicatif::ProgressBar::new(info.total() as u64).with_style(
        indicatif::ProgressStyle::with_template("{msg} {bar:30} {pos}/{len} samples ({per_sec}, ETA {eta})")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_message(format!("{} fields", args.model));
    let (mut indices, mut fields): (Vec<i64>, Vec<f32>) = (Vec::new(), Vec::new());
    let mut grasp_forces: Vec<Vec<[f64; 3]>> = Vec::new();
    for chunk in (0..info.chunks()).filter(|&c| complete[c]) {
        let samples =
            dataset::read_chunk(&args.data, chunk, info.node_count).with_context(|| format!("chunk {chunk}"))?;
        let wanted: Vec<&dataset::SampleRecord> = samples
            .iter()
            .map(|(s, _)| s)
            .filter(|s| (args.split == "all" || s.split == args.split) && !s.failed())
            .collect();
        let answers: Vec<Served> = wanted
            .par_iter()
            .map(|sample| {
                let request = Request {
                    model: args.model.clone(),
                    grasps: sample.grasps(),
                    ..Request::default()
                };
                engine
                    .predict(&request)
                    .map(|p| (p.displacements, p.grasp_forces))
                    .with_context(|| format!("sample {}", sample.index))
            })
            .collect::<anyhow::Result<_>>()?;
        indices.extend(wanted.iter().map(|s| s.index as i64));
        for (field, forces) in answers {
            fields.extend(field);
            grasp_forces.extend(forces);
        }
        bar.inc(samples.len() as u64);
    }
    bar.finish_and_clear();
    if indices.is_empty() {
        anyhow::bail!("no samples in split {:?} of {}", args.split, args.data.display());
    }
    let count = indices.len();
    let displacement = TensorView::new(
        Dtype::F32,
        vec![count, info.node_count, 3],
        bytemuck::cast_slice(&fields),
    )?;
    let index = TensorView::new(Dtype::I64, vec![count], bytemuck::cast_slice(&indices))?;
    let grasps = grasp_forces.iter().map(Vec::len).max().unwrap_or(0);
    let padded: Vec<f32> = grasp_forces
        .iter()
        .flat_map(|forces| (0..grasps).flat_map(move |g| forces.get(g).copied().unwrap_or_default().map(|v| v as f32)))
        .collect();
    let metadata = std::collections::HashMap::from([
        ("model".to_owned(), args.model.clone()),
        ("split".to_owned(), args.split.clone()),
        ("mesh_hash".to_owned(), info.mesh_hash.clone()),
    ]);
    let mut tensors = vec![("displacement", displacement), ("index", index)];
    // Every answer of a model carries forces or none does (ModelInfo.forces).
    if grasp_forces.len() == count {
        let view = TensorView::new(Dtype::F32, vec![count, grasps, 3], bytemuck::cast_slice(&padded))?;
        tensors.push(("grasp_forces", view));
    }
    let bytes = safetensors::serialize(tensors, Some(metadata))?;
    std::fs::write(&args.out, bytes).with_context(|| format!("cannot write {}", args.out.display()))?;
    println!(
        "{}: {} field of {count} {} samples of {}",
        args.out.display(),
        args.model,
        args.split,
        args.data.display()
    );
    Ok(())
}
