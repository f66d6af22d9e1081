//! `nak organ new`: a user's organ, from a segmented surface to what `nak serve --mesh DIR` serves.
//! Stages, each skipped when its output is in place and its inputs have not changed:
//! 1. the labelled volume mesh and `model.toml`, made by the `nak_organ` Python package (gmsh) with
//!    the project's `.venv`, and checked by this binary's `nak mesh info` ([`mesh`]);
//! 2. the Green's functions of green-linear and of green-tangent (with the gravity preload), in nak's
//!    cache, so that the server's first start does not compute them: the exact models are served
//!    from here on;
//! 3. a network ([`network`]): training data and a held-out set of another seed made by `nak
//!    datagen`, the reduced network trained and exported by the `nak_training` package, and scored
//!    on the held-out set through `nak eval`.
//!
//! docs/your-own-organ.md walks through it.

mod mesh;
mod network;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use nak::engine::Regime;
use nak::fem::Stiffness;

use crate::cli::engine::{default_cache_dir, load_green, load_mesh};

#[derive(clap::Args)]
pub struct OrganNewArgs {
    /// A closed triangle surface: .stl (ASCII or binary), .obj or .ply.
    surface: PathBuf,
    /// Units of the surface's coordinates: mm, cm or m.
    #[arg(long)]
    units: String,
    /// The model directory to make (organ.msh, model.toml, the network, data/); `nak serve --mesh
    /// DIR` serves it.
    #[arg(long)]
    out: PathBuf,
    /// Nodes held in place (repeatable, their union): sphere:x,y,z,r | box:x0,y0,z0,x1,y1,z1 |
    /// vertices:i,j,… | group:NAME, in the surface's units.
    #[arg(long, value_name = "SPEC")]
    fixed: Vec<String>,
    /// A grasp region, NAME=SPEC (repeatable); without any, the free surface is split into
    /// --grasp-regions regions of similar area.
    #[arg(long, value_name = "NAME=SPEC")]
    grasp: Vec<String>,
    /// Without --grasp: how many grasp regions the free surface is split into [default: 10].
    #[arg(long, value_name = "N")]
    grasp_regions: Option<usize>,
    /// About this many nodes in the volume mesh.
    #[arg(long, default_value_t = 10_000)]
    target_nodes: usize,
    /// Stop when the exact models are ready: no training data, no network.
    #[arg(long)]
    no_network: bool,
    /// The regime of the network's data: linear (seconds) or nonlinear (hours on two cores; see
    /// docs/your-own-organ.md for more machines).
    #[arg(long, value_enum, default_value_t = Regime::Linear)]
    regime: Regime,
    /// Training samples, split evenly between one and two graspers [default: the paper's 10,400].
    #[arg(long, value_name = "N")]
    samples: Option<usize>,
    /// Held-out samples of another seed the network is scored on.
    #[arg(long, value_name = "N", default_value_t = 1_000)]
    held_out: usize,
    /// The network's training configuration [default: training/configs/pod-res.toml, or
    /// training/configs/nonlinear/pod-res-gt-nl.toml for --regime nonlinear].
    #[arg(long, value_name = "TOML")]
    config: Option<PathBuf>,
    /// Training steps (overrides the configuration's).
    #[arg(long)]
    steps: Option<usize>,
    /// The Python that runs the meshing and training stages (scripts/setup-python --training).
    #[arg(long, default_value = ".venv/bin/python")]
    python: PathBuf,
    /// The directory holding the `nak_organ` package (the repository's `organ/`).
    #[arg(long, default_value = "organ")]
    organ_package: PathBuf,
    /// The directory holding the `nak_training` package (the repository's `training/`).
    #[arg(long, default_value = "training")]
    training_package: PathBuf,
    /// Where the Green's functions and the gravity preload are cached [default: ~/.cache/nak].
    #[arg(long)]
    cache_dir: Option<PathBuf>,
}

pub fn run(args: &OrganNewArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let stages = if args.no_network { 3 } else { 6 };
    mesh::make(args, stages)?;
    let mesh = load_mesh(Some(&args.out))?;
    let cache = args.cache_dir.clone().unwrap_or_else(default_cache_dir);
    for (stage, stiffness) in [(2, Stiffness::Linear), (3, Stiffness::PreloadTangent)] {
        let name = stiffness.model_name();
        let (begun, cached) = (Instant::now(), stiffness.cached(&mesh, &cache));
        let green = load_green(&mesh, stiffness, &cache)?;
        let how = if cached {
            "already cached".to_string()
        } else {
            format!("computed in {:.1} s", begun.elapsed().as_secs_f64())
        };
        println!(
            "[{stage}/{stages}] {name}: {} columns {how}, {}",
            3 * green.candidates().len(),
            green.path.display()
        );
    }
    let serve = format!("nak serve --mesh {} --green-linear --green-tangent", args.out.display());
    println!(
        "{} serves the exact models ({:.1} s): {serve}",
        args.out.display(),
        started.elapsed().as_secs_f64()
    );
    if args.no_network {
        return Ok(());
    }
    let model = network::make(args, &mesh, &cache, stages)?;
    println!(
        "{} is ready ({:.1} s) with the network {model}: {serve}",
        args.out.display(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// The hash of a stage's inputs, kept in a file beside its outputs: the stage is skipped while the
/// file holds the same hash.
struct Stamp {
    path: PathBuf,
    hash: String,
}

impl Stamp {
    fn new(path: PathBuf, hash: String) -> Self {
        Self { path, hash }
    }

    fn is_current(&self) -> bool {
        std::fs::read_to_string(&self.path).is_ok_and(|s| s.trim() == self.hash)
    }

    fn write(&self) -> anyhow::Result<()> {
        std::fs::write(&self.path, format!("{}\n", self.hash))
            .with_context(|| format!("cannot write {}", self.path.display()))
    }
}

/// Adds a Python package's sources (names and bytes) to `hasher`; `flag` names the option that
/// points elsewhere when the package is not where it is looked for.
fn hash_package(hasher: &mut blake3::Hasher, package: &Path, flag: &str) -> anyhow::Result<()> {
    let entries = std::fs::read_dir(package).with_context(|| {
        format!(
            "cannot read the Python package {}: run from the repository's root, or name the directory \
             holding it with {flag}",
            package.display()
        )
    })?;
    let mut sources: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "py"))
        .collect();
    sources.sort();
    for source in sources {
        hasher.update(source.to_string_lossy().as_bytes());
        hasher.update(&std::fs::read(&source).with_context(|| format!("cannot read {}", source.display()))?);
    }
    Ok(())
}
