//! Stage 1 of `nak organ new`: the labelled volume mesh and `model.toml`, made by the `nak_organ`
//! Python package (gmsh) and checked by this binary's `nak mesh info`.

use std::process::Command;
use std::time::Instant;

use anyhow::{Context, bail};

use super::{OrganNewArgs, Stamp, hash_package};

/// What the mesh stage's inputs hash to is kept beside its outputs: run again with the same inputs,
/// the stage is skipped.
const MESH_STAMP: &str = ".nak-organ-mesh";
const MESH_FILES: [&str; 2] = ["organ.msh", "model.toml"];

/// The labelled volume mesh, made again only when the surface, the options or the meshing code
/// changed since the last run (or its files are gone).
pub fn make(args: &OrganNewArgs, stages: usize) -> anyhow::Result<()> {
    let begun = Instant::now();
    let stamp = Stamp::new(args.out.join(MESH_STAMP), inputs_hash(args)?);
    let made = MESH_FILES.iter().all(|f| args.out.join(f).is_file());
    if made && stamp.is_current() {
        println!(
            "[1/{stages}] mesh: {} is up to date, not made again",
            args.out.display()
        );
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
    stamp.write()?;
    println!("[1/{stages}] mesh: made in {:.1} s", begun.elapsed().as_secs_f64());
    Ok(())
}

/// A hash of everything the mesh stage reads: the surface's bytes, the options, and the meshing
/// package's sources.
fn inputs_hash(args: &OrganNewArgs) -> anyhow::Result<String> {
    let mut hasher = blake3::Hasher::new();
    let surface =
        std::fs::read(&args.surface).with_context(|| format!("cannot read the surface {}", args.surface.display()))?;
    hasher.update(&surface);
    let options = format!(
        "{}|{:?}|{:?}|{:?}|{}",
        args.units, args.fixed, args.grasp, args.grasp_regions, args.target_nodes
    );
    hasher.update(options.as_bytes());
    hash_package(&mut hasher, &args.organ_package.join("nak_organ"), "--organ-package")?;
    Ok(hasher.finalize().to_hex().to_string())
}
