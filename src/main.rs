//! The `nak` command line: serve, predict, and inspect meshes.

mod cli;

use std::path::PathBuf;

use anyhow::Context;
use clap::{Parser, Subcommand};
use nak::mesh::{self, MeshSource};

#[derive(Parser)]
#[command(
    name = "nak",
    version,
    about = "Real-time soft-tissue deformation server (Neural-Augmented Kelvinlet)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Inspect meshes.
    Mesh {
        #[command(subcommand)]
        command: MeshCommand,
    },
}

#[derive(Subcommand)]
enum MeshCommand {
    /// Load and validate a mesh, and print a summary: counts, bounds, regions, node sets, quality.
    Info {
        /// A model directory (its default mesh) or an .msh file with model.toml beside it; omitted: the
        /// embedded phantom liver.
        path: Option<PathBuf>,
    },
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Mesh {
            command: MeshCommand::Info { path },
        } => {
            let source = MeshSource::from_arg(path.as_deref());
            let mesh = mesh::load(&source).with_context(|| format!("cannot load mesh {source}"))?;
            print_or_pipe_closed(|out| cli::mesh_info::print(out, &mesh))?;
        }
    }
    Ok(())
}

/// Writes to stdout; a reader that goes away early (`nak mesh info | head`) is not an error.
fn print_or_pipe_closed(
    f: impl FnOnce(&mut std::io::StdoutLock) -> std::io::Result<()>,
) -> anyhow::Result<()> {
    match f(&mut std::io::stdout().lock()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        other => Ok(other?),
    }
}
