//! `nak mesh refine`: a finer mesh of the same organ, for measuring what a larger mesh costs (the
//! GPU prior pays off from about 100,000 nodes).

use std::path::{Path, PathBuf};

use anyhow::Context;
use nak::mesh::{self, MeshSource};

#[derive(clap::Args)]
pub struct RefineArgs {
    /// A model directory, a mesh file with model.toml beside it, or "embedded".
    input: PathBuf,
    /// The refined mesh: a .vtu (or legacy .vtk) file.
    output: PathBuf,
    /// Times to split: each level multiplies the tetrahedra by 8 and the nodes by about 7.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=3))]
    levels: u32,
}

pub fn run(args: &RefineArgs) -> anyhow::Result<()> {
    if mesh::vtk::format(&args.output).is_none() {
        anyhow::bail!(
            "{}: the refined mesh is written as VTK: name it .vtu or .vtk",
            args.output.display()
        );
    }
    let input = (args.input.as_os_str() != "embedded").then_some(args.input.as_path());
    let source = MeshSource::from_arg(input);
    let mut refined = super::engine::load_mesh(input)?;
    let coarse = (refined.node_count(), refined.tets.len());
    for level in 1..=args.levels {
        refined = refined
            .refined()
            .with_context(|| format!("refinement level {level} of {source} failed validation"))?;
    }
    if let Some(dir) = args.output.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    mesh::vtk::write(&refined, None, &args.output)?;
    println!(
        "{source} ({} nodes, {} tetrahedra) → {} ({} nodes, {} tetrahedra, {} on the surface)",
        coarse.0,
        coarse.1,
        args.output.display(),
        refined.node_count(),
        refined.tets.len(),
        refined.surface_nodes.len()
    );
    write_config_beside(&source, &args.output)
}

/// Writes the source's model.toml beside `output`, its default mesh now `output`, unless the
/// directory has a model.toml already (then that one configures the refined mesh, and is named).
fn write_config_beside(source: &MeshSource, output: &Path) -> anyhow::Result<()> {
    let dir = output
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let path = dir.join("model.toml");
    if path.exists() {
        println!("{} configures it (left as it is)", path.display());
        return Ok(());
    }
    let name = output.file_name().map(|n| n.to_string_lossy()).unwrap_or_default();
    let text = mesh::config_text(source)?;
    let config: String = text
        .lines()
        .map(|line| match line.trim_start().starts_with("default =") {
            true => format!("default = {name:?}\n"),
            false => format!("{line}\n"),
        })
        .collect();
    std::fs::write(&path, config).with_context(|| format!("cannot write {}", path.display()))?;
    println!("{} written from {source}'s configuration", path.display());
    Ok(())
}
