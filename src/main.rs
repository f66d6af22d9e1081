//! The `nak` command line: parses the subcommand and hands it to its module in `cli/`.

mod cli;

use std::path::PathBuf;

use clap::{Parser, Subcommand, ValueEnum};

#[derive(Parser)]
#[command(
    name = "nak",
    version,
    about = "Real-time soft-tissue deformation server (Neural-Augmented Kelvinlet)"
)]
struct Cli {
    /// Log format on stderr (filter with RUST_LOG, e.g. RUST_LOG=nak=debug).
    #[arg(long, global = true, value_enum, default_value_t = LogFormat::Text)]
    log_format: LogFormat,
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
enum LogFormat {
    Text,
    Json,
}

#[derive(Subcommand)]
enum Command {
    /// Serve deformation predictions over gRPC (defaults: embedded phantom liver, 127.0.0.1:50051).
    Serve(Box<cli::serve::ServeArgs>),
    /// Evaluate one set of grasps offline through the serving engine; write the field as .npy or the
    /// deformed mesh as .vtu/.vtk.
    Predict(cli::predict::PredictArgs),
    /// Load-test a nak server: open or closed loop, unary or streaming, HDR latency percentiles.
    Bench(cli::bench::BenchArgs),
    /// Generate a dataset: grasps from the paper's distribution p with finite-element ground truth.
    Datagen(cli::datagen::DatagenArgs),
    /// Work with datasets.
    Dataset {
        #[command(subcommand)]
        command: DatasetCommand,
    },
    /// Evaluate a model on a dataset with the paper's DCM metric.
    Eval {
        #[command(flatten)]
        eval: cli::eval::EvalArgs,
        /// The dataset's mesh [default: the embedded phantom liver].
        #[arg(long)]
        mesh: Option<PathBuf>,
        #[command(flatten)]
        models: cli::engine::ModelArgs,
    },
    /// Re-send the requests of an MCAP recording and compare the answers with the recorded ones.
    Replay(cli::replay::ReplayArgs),
    /// Inspect meshes.
    Mesh {
        #[command(subcommand)]
        command: MeshCommand,
    },
    /// Your own organ, from a segmented surface to a served model.
    Organ {
        #[command(subcommand)]
        command: OrganCommand,
    },
}

#[derive(Subcommand)]
enum OrganCommand {
    /// From a closed surface (STL, OBJ, PLY): a labelled volume mesh and model.toml, then the Green's
    /// functions of green-linear and green-tangent, so that `nak serve --mesh DIR` serves it at once.
    /// Run again, it redoes only what changed.
    New(cli::organ::OrganNewArgs),
}

#[derive(Subcommand)]
enum DatasetCommand {
    /// Check that directories made by `nak datagen --shard I/N` are every shard of one dataset,
    /// each complete, and assemble them into the dataset an unsharded run makes.
    Join(cli::dataset::JoinArgs),
    /// Write a served model's field for every sample of a dataset split (training's priors).
    Fields {
        #[command(flatten)]
        fields: cli::fields::FieldsArgs,
        /// The dataset's mesh [default: the embedded phantom liver].
        #[arg(long)]
        mesh: Option<PathBuf>,
        #[command(flatten)]
        models: cli::engine::ModelArgs,
    },
}

#[derive(Subcommand)]
enum MeshCommand {
    /// Load and validate a mesh, and print a summary: counts, bounds, regions, node sets, quality.
    Info {
        /// A model directory (its default mesh) or a mesh file (.msh, .vtu, .vtk) with model.toml
        /// beside it [default: the embedded phantom liver].
        path: Option<PathBuf>,
    },
    /// Write a mesh as a VTK unstructured grid (.vtu or legacy .vtk, by extension) with its regions
    /// and node sets, after the same validation as serving it.
    Convert {
        /// A model directory, a mesh file with model.toml beside it, or "embedded".
        input: PathBuf,
        output: PathBuf,
    },
    /// Split every tetrahedron into eight at its edge midpoints (about 7× the nodes per level) and
    /// write the finer mesh as a VTK unstructured grid, with a model.toml beside it if there is none.
    Refine(cli::mesh_refine::RefineArgs),
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    init_logging(cli.log_format);
    match cli.command {
        Command::Serve(args) => cli::serve::run(*args),
        Command::Predict(args) => cli::predict::run(args),
        Command::Bench(args) => cli::bench::run(args),
        Command::Replay(args) => cli::replay::run(args),
        Command::Datagen(args) => {
            let mesh = cli::engine::load_mesh(args.mesh.as_deref())?;
            let cache = args.cache_dir.clone().unwrap_or_else(cli::engine::default_cache_dir);
            cli::datagen::run(args, &mesh, cache)
        }
        Command::Dataset {
            command: DatasetCommand::Join(args),
        } => cli::dataset::join(&args),
        Command::Dataset {
            command: DatasetCommand::Fields { fields, mesh, models },
        } => {
            let engine = models.engine(mesh, &fields.model)?;
            cli::fields::run(&fields, &engine)
        }
        Command::Eval { eval, mesh, models } => {
            let engine = models.engine(mesh, &eval.model)?;
            cli::eval::run(&eval, &engine)
        }
        Command::Organ {
            command: OrganCommand::New(args),
        } => cli::organ::run(&args),
        Command::Mesh {
            command: MeshCommand::Info { path },
        } => {
            let mesh = cli::engine::load_mesh(path.as_deref())?;
            print_or_pipe_closed(|out| cli::mesh_info::print(out, &mesh))
        }
        Command::Mesh {
            command: MeshCommand::Refine(args),
        } => cli::mesh_refine::run(&args),
        Command::Mesh {
            command: MeshCommand::Convert { input, output },
        } => {
            let input = (input.as_os_str() != "embedded").then_some(input);
            let mesh = cli::engine::load_mesh(input.as_deref())?;
            nak::mesh::vtk::write(&mesh, None, &output)?;
            println!(
                "{} → {} ({} nodes, {} tetrahedra)",
                mesh.origin,
                output.display(),
                mesh.node_count(),
                mesh.tets.len()
            );
            Ok(())
        }
    }
}

fn init_logging(format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        // ONNX Runtime logs every session option at info; its warnings are what matter.
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info,ort=warn"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    match format {
        LogFormat::Text => builder.init(),
        LogFormat::Json => builder.json().init(),
    }
}

/// Writes to stdout; a reader that goes away early (`nak mesh info | head`) is not an error.
fn print_or_pipe_closed(f: impl FnOnce(&mut std::io::StdoutLock) -> std::io::Result<()>) -> anyhow::Result<()> {
    match f(&mut std::io::stdout().lock()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        other => Ok(other?),
    }
}
