//! `nak organ new`: a user's organ, from a segmented surface to what `nak serve --mesh DIR` serves at
//! once. Two stages, each skipped when its output is in place and its inputs have not changed:
//! 1. the labelled volume mesh and `model.toml`, made by the `nak_organ` Python package (gmsh) with
//!    the project's `.venv`, and checked by this binary's `nak mesh info`;
//! 2. the Green's functions of green-linear and of green-tangent (with the gravity preload), in nak's
//!    cache, so that the server's first start does not compute them.
//!
//! docs/your-own-organ.md walks through it.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, bail};
use nak::fem::Stiffness;

use crate::cli::engine::{default_cache_dir, load_green, load_mesh};

/// What the mesh stage's inputs hash to is kept beside its outputs: run again with the same inputs,
/// the stage is skipped.
const MESH_STAMP: &str = ".nak-organ-mesh";
const MESH_FILES: [&str; 2] = ["organ.msh", "model.toml"];

#[derive(clap::Args)]
pub struct OrganNewArgs {
    /// A closed triangle surface: .stl (ASCII or binary), .obj or .ply.
    surface: PathBuf,
    /// Units of the surface's coordinates: mm, cm or m.
    #[arg(long)]
    units: String,
    /// The model directory to make (organ.msh, model.toml); `nak serve --mesh DIR` serves it.
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
    /// The Python that runs the meshing stage (it needs gmsh and meshio: scripts/setup-python).
    #[arg(long, default_value = ".venv/bin/python")]
    python: PathBuf,
    /// The directory holding the `nak_organ` package (the repository's `organ/`).
    #[arg(long, default_value = "organ")]
    organ_package: PathBuf,
    /// Where the Green's functions and the gravity preload are cached [default: ~/.cache/nak].
    #[arg(long)]
    cache_dir: Option<PathBuf>,
}

pub fn run(args: &OrganNewArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    mesh_stage(args)?;
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
            "[{stage}/3] {name}: {} columns {how}, {}",
            3 * green.candidates().len(),
            green.path.display()
        );
    }
    println!(
        "{} is ready ({:.1} s): nak serve --mesh {} --green-linear --green-tangent",
        args.out.display(),
        started.elapsed().as_secs_f64(),
        args.out.display()
    );
    Ok(())
}

/// The labelled volume mesh, made again only when the surface, the options or the meshing code
/// changed since the last run (or its files are gone).
fn mesh_stage(args: &OrganNewArgs) -> anyhow::Result<()> {
    let begun = Instant::now();
    let stamp = mesh_inputs_hash(args)?;
    let stamp_path = args.out.join(MESH_STAMP);
    let made = MESH_FILES.iter().all(|f| args.out.join(f).is_file());
    if made && std::fs::read_to_string(&stamp_path).is_ok_and(|s| s.trim() == stamp) {
        println!("[1/3] mesh: {} is up to date, not made again", args.out.display());
        return Ok(());
    }
    let mut command = Command::new(&args.python);
    command
        .env("PYTHONPATH", &args.organ_package)
        .args(["-m", "nak_organ", "mesh"])
        .arg(&args.surface)
        .args(["--units", &args.units, "--target-nodes", &args.target_nodes.to_string()])
        .arg("--out")
        .arg(&args.out)
        .arg("--nak")
        .arg(std::env::current_exe().context("cannot find this nak binary to check the mesh with")?);
    for spec in &args.fixed {
        command.args(["--fixed", spec]);
    }
    for spec in &args.grasp {
        command.args(["--grasp", spec]);
    }
    if let Some(regions) = args.grasp_regions {
        command.args(["--grasp-regions", &regions.to_string()]);
    }
    let status = command.status().with_context(|| {
        format!(
            "cannot run {} for the meshing stage: make the Python tooling with scripts/setup-python, or \
             name a Python with gmsh and meshio with --python",
            args.python.display()
        )
    })?;
    if !status.success() {
        // The package printed what it refused and where; nothing was placed in --out.
        bail!("the meshing stage did not make {} (above: why)", args.out.display());
    }
    std::fs::write(&stamp_path, format!("{stamp}\n"))
        .with_context(|| format!("cannot write {}", stamp_path.display()))?;
    println!("[1/3] mesh: made in {:.1} s", begun.elapsed().as_secs_f64());
    Ok(())
}

/// A hash of everything the mesh stage reads: the surface's bytes, the options, and the meshing
/// package's sources.
fn mesh_inputs_hash(args: &OrganNewArgs) -> anyhow::Result<String> {
    let mut hasher = blake3::Hasher::new();
    let surface =
        std::fs::read(&args.surface).with_context(|| format!("cannot read the surface {}", args.surface.display()))?;
    hasher.update(&surface);
    let options = format!(
        "{}|{:?}|{:?}|{:?}|{}",
        args.units, args.fixed, args.grasp, args.grasp_regions, args.target_nodes
    );
    hasher.update(options.as_bytes());
    for source in package_sources(&args.organ_package.join("nak_organ"))? {
        hasher.update(source.to_string_lossy().as_bytes());
        hasher.update(&std::fs::read(&source).with_context(|| format!("cannot read {}", source.display()))?);
    }
    Ok(hasher.finalize().to_hex().to_string())
}

fn package_sources(package: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(package).with_context(|| {
        format!(
            "cannot read the meshing package {}: run from the repository's root, or name the directory \
             holding nak_organ with --organ-package",
            package.display()
        )
    })?;
    let mut sources: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "py"))
        .collect();
    sources.sort();
    Ok(sources)
}
