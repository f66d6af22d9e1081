//! Stages 4–6 of `nak organ new`: a network for the organ. Training data and a held-out set of
//! another seed are made by `nak datagen` (in this process; each resumes chunk by chunk), the
//! network is trained and exported by the `nak_training` package (its checkpoints resume; export
//! checks ONNX Runtime's answer against PyTorch's), then scored on the held-out set through
//! `nak eval`, its figures written into its manifest.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, bail};
use nak::engine::Regime;
use nak::mesh::TetMesh;
use nak::model::Manifest;

use super::{OrganNewArgs, Stamp, hash_package};
use crate::cli::datagen::{self, DatagenArgs};

/// The seeds of the training data and of the held-out set the network is scored on.
const TRAIN_SEED: u64 = 0;
const HELD_OUT_SEED: u64 = 1;
/// The paper preset's size (5,000 single-grasper and 5,400 two-grasper samples).
const PAPER_SAMPLES: usize = 10_400;
/// The inputs a trained network was made from, beside it and beside its checkpoints.
const NETWORK_STAMP: &str = ".nak-organ-network";

/// The training configuration `nak organ new` uses for `regime` when none is given.
fn default_config(regime: Regime) -> &'static str {
    match regime {
        Regime::Linear => "training/configs/pod-res.toml",
        Regime::Nonlinear => "training/configs/nonlinear/pod-res-gt-nl.toml",
    }
}

/// Makes (or finds up to date) the organ's network; returns its name.
pub fn make(args: &OrganNewArgs, mesh: &TetMesh, cache: &Path, stages: usize) -> anyhow::Result<String> {
    let begun = Instant::now();
    let train = dataset(args, mesh, cache, TRAIN_SEED, args.samples)?;
    let held_out = dataset(args, mesh, cache, HELD_OUT_SEED, Some(args.held_out))?;
    println!(
        "[4/{stages}] data: {} (training) and {} (held out) in {:.1} s",
        train.display(),
        held_out.display(),
        begun.elapsed().as_secs_f64()
    );

    let config = args
        .config
        .clone()
        .unwrap_or_else(|| default_config(args.regime).into());
    let name = config_name(&config)?;
    let model_dir = args.out.join(&name);
    let stamp = Stamp::new(
        model_dir.join(NETWORK_STAMP),
        inputs_hash(args, mesh, &config, &train, &held_out)?,
    );
    if model_dir.join("manifest.toml").is_file() && stamp.is_current() {
        println!(
            "[5/{stages}] network: {} is up to date, not trained again",
            model_dir.display()
        );
        println!("[6/{stages}] score: {}", score(&model_dir)?);
        return Ok(name);
    }
    check_training_python(args)?;
    let runs = args.out.join("data").join("runs");
    let run_dir = runs.join(&name);
    let run_stamp = Stamp::new(run_dir.join(NETWORK_STAMP), stamp.hash.clone());
    if run_dir.exists() && !run_stamp.is_current() {
        // Checkpoints of other data or another configuration: resuming them would mix the two.
        std::fs::remove_dir_all(&run_dir).with_context(|| format!("cannot remove {}", run_dir.display()))?;
    }
    std::fs::create_dir_all(&run_dir).with_context(|| format!("cannot make {}", run_dir.display()))?;
    run_stamp.write()?;

    let begun = Instant::now();
    for step in ["train", "export"] {
        run_training(training_command(args, cache, step, &config, &train, &runs)?, step)?;
    }
    println!(
        "[5/{stages}] network: {} trained and exported in {:.1} s (ONNX Runtime checked against PyTorch)",
        model_dir.display(),
        begun.elapsed().as_secs_f64()
    );
    let begun = Instant::now();
    let mut evaluate = training_command(args, cache, "evaluate", &config, &held_out, &runs)?;
    evaluate.args(["--split", "all"]);
    run_training(evaluate, "evaluate")?;
    stamp.write()?;
    println!(
        "[6/{stages}] score: {} ({:.1} s)",
        score(&model_dir)?,
        begun.elapsed().as_secs_f64()
    );
    Ok(name)
}

/// The dataset of `seed` (`samples` of them, or the paper preset), made or resumed under
/// `DIR/data`, named after what it holds so that a changed mesh or size makes a new one.
fn dataset(
    args: &OrganNewArgs,
    mesh: &TetMesh,
    cache: &Path,
    seed: u64,
    samples: Option<usize>,
) -> anyhow::Result<PathBuf> {
    let regime = args.regime.name();
    let total = samples.unwrap_or(PAPER_SAMPLES);
    let hash = mesh.content_hash.get(..8).unwrap_or(&mesh.content_hash);
    let dir = args
        .out
        .join("data")
        .join(format!("{regime}-seed{seed}-{total}-{hash}"));
    let mut words: Vec<String> = vec!["--regime".into(), regime.into(), "--seed".into(), seed.to_string()];
    if let Some(n) = samples {
        anyhow::ensure!(
            n >= 2,
            "--samples and --held-out need at least 2 samples (one of each grasp count)"
        );
        words.extend([
            "--single".into(),
            (n / 2).to_string(),
            "--multi".into(),
            (n - n / 2).to_string(),
        ]);
    }
    words.extend(["--out".into(), dir.display().to_string()]);
    // The same set can be made elsewhere, in shards (docs/your-own-organ.md#the-nonlinear-regime).
    println!("      nak datagen --mesh {} {}", args.out.display(), words.join(" "));
    datagen::run(DatagenArgs::from_words(&words)?, mesh, cache.to_path_buf())?;
    Ok(dir)
}

/// The model name a training configuration gives its network (its directory under DIR).
fn config_name(config: &Path) -> anyhow::Result<String> {
    let text = std::fs::read_to_string(config).with_context(|| {
        format!(
            "cannot read the training configuration {}: run from the repository's root, or name one with --config",
            config.display()
        )
    })?;
    let table: toml::Table = text
        .parse()
        .with_context(|| format!("{} is not TOML", config.display()))?;
    match table.get("name").and_then(|n| n.as_str()) {
        Some(name) => Ok(name.to_owned()),
        None => bail!("{} names no model (its `name` key)", config.display()),
    }
}

/// A hash of everything the network stages read: the mesh, the configuration and step count, the
/// two datasets (named after their mesh, seed and size) and the training package's sources.
fn inputs_hash(
    args: &OrganNewArgs,
    mesh: &TetMesh,
    config: &Path,
    train: &Path,
    held_out: &Path,
) -> anyhow::Result<String> {
    let mut hasher = blake3::Hasher::new();
    hasher.update(mesh.content_hash.as_bytes());
    hasher.update(&std::fs::read(config).with_context(|| format!("cannot read {}", config.display()))?);
    let options = format!("{:?}|{}|{}", args.steps, train.display(), held_out.display());
    hasher.update(options.as_bytes());
    hash_package(
        &mut hasher,
        &args.training_package.join("nak_training"),
        "--training-package",
    )?;
    Ok(hasher.finalize().to_hex().to_string())
}

/// Refuses early, with the fix, when the Python cannot train (no PyTorch or ONNX Runtime).
fn check_training_python(args: &OrganNewArgs) -> anyhow::Result<()> {
    let works = Command::new(&args.python)
        .args(["-c", "import torch, onnxruntime"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !works {
        bail!(
            "{} cannot import PyTorch and ONNX Runtime, which the training stage needs: install them with \
             scripts/setup-python --training, name another Python with --python, or stop at the exact \
             models with --no-network",
            args.python.display()
        );
    }
    Ok(())
}

/// Runs one `python -m nak_training` step, its output shown as it runs.
fn run_training(mut command: Command, step: &str) -> anyhow::Result<()> {
    let status = command.status().context("cannot run the training package")?;
    if !status.success() {
        bail!(
            "the training package's {step} step failed (above: why); the same command resumes from the last \
             checkpoint"
        );
    }
    Ok(())
}

/// The `python -m nak_training STEP` command for the organ: its mesh, this nak, and the cache the
/// exact models' Green's functions are in.
fn training_command(
    args: &OrganNewArgs,
    cache: &Path,
    step: &str,
    config: &Path,
    data: &Path,
    runs: &Path,
) -> anyhow::Result<Command> {
    let nak = std::env::current_exe().context("cannot find this nak binary for the training package")?;
    let mut command = Command::new(&args.python);
    command
        .env("PYTHONPATH", &args.training_package)
        .env("NAK_CACHE_DIR", cache)
        .args(["-m", "nak_training", step, "--config"])
        .arg(config)
        .arg("--data")
        .arg(data)
        .arg("--runs")
        .arg(runs)
        .arg("--out")
        .arg(&args.out)
        .arg("--mesh")
        .arg(&args.out)
        .arg("--nak")
        .arg(nak);
    if let Some(steps) = args.steps {
        command.args(["--steps", &steps.to_string()]);
    }
    Ok(command)
}

/// The network's held-out score and time per request, from its manifest's [metrics].
fn score(model_dir: &Path) -> anyhow::Result<String> {
    let path = model_dir.join("manifest.toml");
    let text = std::fs::read_to_string(&path).with_context(|| format!("cannot read {}", path.display()))?;
    let manifest = Manifest::parse(&text, &path.display().to_string())?;
    let figure = |key: &str| {
        let value = manifest.metrics.get(key)?;
        value.as_float().or(value.as_integer().map(|i| i as f64))
    };
    match (figure("dcm_combined"), figure("samples_combined")) {
        (Some(dcm), Some(samples)) => Ok(format!(
            "DCM {dcm:.2} % on {samples} held-out samples of seed {HELD_OUT_SEED} (single grasper {:.2} %, two {:.2} %), \
             {:.2} ms a request",
            figure("dcm_single").unwrap_or(f64::NAN),
            figure("dcm_multi").unwrap_or(f64::NAN),
            figure("total_ms_p50").unwrap_or(f64::NAN),
        )),
        _ => bail!(
            "{} has no scores in [metrics]: run the same command again",
            path.display()
        ),
    }
}
