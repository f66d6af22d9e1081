//! The `nak` command line: serve, predict, and inspect meshes.

mod cli;

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::Context;
use clap::{Parser, Subcommand, ValueEnum};
use nak::engine::{DeformationModel, Engine, RefusedModel};
use nak::fem::{GreenLinear, GreenLinearModel};
use nak::mesh::{self, MeshSource, TetMesh};
use nak::prior::PriorBackend;
use nak::record::{Payload, Recorder};
use nak::serve::{self, ServeConfig};
use tracing::info;

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
    Serve(ServeArgs),
    /// Evaluate one set of grasps offline through the serving engine and write the field as .npy.
    Predict(PredictArgs),
    /// Load-test a nak server: open or closed loop, unary or streaming, HDR latency percentiles.
    Bench(cli::bench::BenchArgs),
    /// Generate a dataset: grasps from the paper's distribution p with finite-element ground truth.
    Datagen(cli::datagen::DatagenArgs),
    /// Evaluate a model on a dataset with the paper's DCM metric.
    Eval {
        #[command(flatten)]
        eval: cli::eval::EvalArgs,
        /// The dataset's mesh [default: the embedded phantom liver].
        #[arg(long)]
        mesh: Option<PathBuf>,
        #[command(flatten)]
        models: ModelArgs,
    },
    /// Re-send the requests of an MCAP recording and compare the answers with the recorded ones.
    Replay(cli::replay::ReplayArgs),
    /// Inspect meshes.
    Mesh {
        #[command(subcommand)]
        command: MeshCommand,
    },
}

#[derive(clap::Args)]
struct ServeArgs {
    /// TOML file with any of: mesh, models, ort_dylib, listen, max_displacement_mm,
    /// max_interaction_points, max_message_bytes, max_in_flight. Flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// A model directory (its default mesh) or an .msh file with model.toml beside it
    /// [default: the embedded phantom liver].
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// Address to listen on [default: 127.0.0.1:50051; port 0 picks a free port].
    #[arg(long)]
    listen: Option<SocketAddr>,
    /// Largest grasp displacement accepted, millimetres [default: 200].
    #[arg(long)]
    max_displacement_mm: Option<f64>,
    /// Most interaction points (grasped nodes) per request [default: 256].
    #[arg(long)]
    max_interaction_points: Option<usize>,
    /// Largest request message, bytes [default: 1048576].
    #[arg(long)]
    max_message_bytes: Option<usize>,
    /// Most requests computed or waiting for the compute pool at once; more are refused at once
    /// with RESOURCE_EXHAUSTED [default: 4 per core].
    #[arg(long)]
    max_in_flight: Option<usize>,
    #[command(flatten)]
    models: ModelArgs,
    /// Record every exchange to MCAP files in this directory (open them in Foxglove or with `nak replay`).
    #[arg(long, value_name = "DIR")]
    record: Option<PathBuf>,
    /// Displacements written per answer [default: surface].
    #[arg(long, value_enum)]
    record_payload: Option<Payload>,
    /// Start a new recording file after this many MiB [default: 1024].
    #[arg(long)]
    record_rotate_mb: Option<u64>,
    /// Start a new recording file after this many minutes [default: 60].
    #[arg(long)]
    record_rotate_minutes: Option<u64>,
    /// Exchanges queued for the recorder before new ones are dropped (never delayed) [default: 4096].
    #[arg(long)]
    record_queue: Option<usize>,
    /// Most deformed-surface point clouds per second on the Foxglove channel [default: 30].
    #[arg(long)]
    record_scene_hz: Option<f64>,
}

/// Where networks come from, and the exact linear model.
#[derive(clap::Args)]
struct ModelArgs {
    /// Also serve `green-linear`, the exact linear FEM answer through precomputed Green's functions
    /// (computed on first use and cached; see --cache-dir).
    #[arg(long)]
    green_linear: bool,
    /// Where green-linear's Green's functions are cached [default: $XDG_CACHE_HOME/nak or ~/.cache/nak].
    #[arg(long, value_name = "DIR")]
    cache_dir: Option<PathBuf>,
    /// A directory whose subdirectories are models (manifest.toml + model.onnx); repeatable. A --mesh
    /// directory is always searched.
    #[arg(long = "models", value_name = "DIR")]
    dirs: Vec<PathBuf>,
    /// ONNX Runtime shared library (libonnxruntime.so.1.31.1) [default: $ORT_DYLIB_PATH].
    #[arg(long, value_name = "PATH")]
    ort_dylib: Option<PathBuf>,
    /// Where the Kelvinlet field is evaluated; `auto` times both at start-up [default: cpu].
    #[arg(long, value_enum)]
    prior_backend: Option<PriorBackend>,
}

#[derive(clap::Args)]
struct PredictArgs {
    /// A model directory or an .msh file [default: the embedded phantom liver].
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// Model to evaluate.
    #[arg(long, default_value = "kelvinlet")]
    model: String,
    /// JSON: {"grasps": [{"nodes": [...], "displacement": [dx, dy, dz]}, {"point": [x, y, z],
    /// "radius": r, "displacement": [...]}]}, metres.
    #[arg(long)]
    grasps: PathBuf,
    /// Output .npy, float32 (N, 3).
    #[arg(long)]
    out: PathBuf,
    /// Write the surface nodes only (Mesh.surface_nodes order) instead of every node.
    #[arg(long)]
    surface_only: bool,
    #[command(flatten)]
    models: ModelArgs,
}

#[derive(Subcommand)]
enum MeshCommand {
    /// Load and validate a mesh, and print a summary: counts, bounds, regions, node sets, quality.
    Info {
        /// A model directory (its default mesh) or an .msh file with model.toml beside it
        /// [default: the embedded phantom liver].
        path: Option<PathBuf>,
    },
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    init_logging(cli.log_format);
    match cli.command {
        Command::Serve(args) => serve(args),
        Command::Predict(args) => predict(args),
        Command::Bench(args) => cli::bench::run(args),
        Command::Replay(args) => cli::replay::run(args),
        Command::Datagen(args) => {
            let mesh = load_mesh(args.mesh.as_deref())?;
            let cache = args.cache_dir.clone().unwrap_or_else(default_cache_dir);
            cli::datagen::run(args, &mesh, cache)
        }
        Command::Eval { eval, mesh, models } => {
            let config = ServeConfig {
                mesh,
                models: models.dirs,
                ort_dylib: models.ort_dylib,
                // green-linear is evaluated when asked for by name.
                green_linear: models.green_linear || eval.model == GreenLinearModel::NAME,
                cache_dir: models.cache_dir,
                prior_backend: models.prior_backend.unwrap_or_default(),
                ..ServeConfig::default()
            };
            cli::eval::run(&eval, &build_engine(&config)?)
        }
        Command::Mesh {
            command: MeshCommand::Info { path },
        } => {
            let mesh = load_mesh(path.as_deref())?;
            print_or_pipe_closed(|out| cli::mesh_info::print(out, &mesh))
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

fn load_mesh(path: Option<&Path>) -> anyhow::Result<TetMesh> {
    let source = MeshSource::from_arg(path);
    mesh::load(&source).with_context(|| format!("cannot load mesh {source}"))
}

fn serve_config(args: ServeArgs) -> anyhow::Result<ServeConfig> {
    let mut config = match &args.config {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
            toml::from_str(&text).with_context(|| format!("{}: invalid serve configuration", path.display()))?
        }
        None => ServeConfig::default(),
    };
    config.mesh = args.mesh.or(config.mesh);
    config.listen = args.listen.unwrap_or(config.listen);
    config.max_displacement_mm = args.max_displacement_mm.unwrap_or(config.max_displacement_mm);
    config.max_interaction_points = args.max_interaction_points.unwrap_or(config.max_interaction_points);
    config.max_message_bytes = args.max_message_bytes.unwrap_or(config.max_message_bytes);
    config.max_in_flight = args.max_in_flight.unwrap_or(config.max_in_flight);
    config.models.extend(args.models.dirs);
    config.green_linear |= args.models.green_linear;
    config.cache_dir = args.models.cache_dir.or(config.cache_dir);
    config.record = args.record.or(config.record);
    config.record_payload = args.record_payload.unwrap_or(config.record_payload);
    config.record_rotate_mb = args.record_rotate_mb.unwrap_or(config.record_rotate_mb);
    config.record_rotate_minutes = args.record_rotate_minutes.unwrap_or(config.record_rotate_minutes);
    config.record_queue = args.record_queue.unwrap_or(config.record_queue);
    config.record_scene_hz = args.record_scene_hz.unwrap_or(config.record_scene_hz);
    config.ort_dylib = args.models.ort_dylib.or(config.ort_dylib);
    config.prior_backend = args.models.prior_backend.unwrap_or(config.prior_backend);
    Ok(config)
}

/// The mesh, the Kelvinlet prior and every model found under the configured directories.
fn build_engine(config: &ServeConfig) -> anyhow::Result<Engine> {
    let mesh = Arc::new(load_mesh(config.mesh.as_deref())?);
    let mut engine = Engine::new(mesh.clone(), config.limits());
    let choice = engine
        .use_prior_backend(config.prior_backend)
        .context("cannot use the GPU prior (--prior-backend gpu); `auto` falls back to the CPU")?;
    info!("{choice}");
    if config.mesh.is_none() {
        load_shipped_models(&mut engine, &mesh, config.ort_dylib.as_deref())?;
    }
    for root in config.model_roots() {
        let models = nak::model::load_each(&root, &mesh, config.ort_dylib.as_deref())
            .with_context(|| format!("cannot read the model directory {}", root.display()))?;
        for model in models {
            match model {
                Ok(model) => {
                    info!(model = %model.info().name, from = %root.display(), "model loaded and warmed up");
                    engine.add_model(Arc::new(model));
                }
                // One bad model must not take the others down: refuse it loudly and serve the rest.
                Err(e) => {
                    tracing::error!(model = %e.origin, "model refused, not served: {}", e.message);
                    engine.refuse_model(RefusedModel {
                        origin: e.origin,
                        reason: e.message,
                    });
                }
            }
        }
    }
    if config.green_linear {
        engine.add_model(Arc::new(green_linear(&mesh, config)?));
    }
    Ok(engine)
}

/// The networks shipped with the embedded phantom. Without ONNX Runtime the server still starts and
/// serves the prior, saying what it left out and how to get it.
fn load_shipped_models(engine: &mut Engine, mesh: &TetMesh, ort_dylib: Option<&Path>) -> anyhow::Result<()> {
    let shipped = nak::model::shipped::SHIPPED;
    if shipped.is_empty() {
        return Ok(());
    }
    if let Err(e) = nak::model::runtime::locate(ort_dylib) {
        let names: Vec<&str> = shipped.iter().map(|m| m.name).collect();
        tracing::warn!("the shipped networks {names:?} are not served: {e}");
        return Ok(());
    }
    for model in nak::model::shipped::load(mesh, ort_dylib).context("cannot load the shipped networks")? {
        info!(model = %model.info().name, "shipped model loaded and warmed up");
        engine.add_model(Arc::new(model));
    }
    Ok(())
}

/// Loads green-linear's Green's functions from the cache, computing them with a progress bar first.
fn green_linear(mesh: &TetMesh, config: &ServeConfig) -> anyhow::Result<GreenLinearModel> {
    let cache = config.cache_dir.clone().unwrap_or_else(default_cache_dir);
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template("Green's functions {bar:30} {pos}/{len} columns, ETA {eta}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let green = GreenLinear::load_or_compute(mesh, &cache, |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })
    .with_context(|| format!("cannot prepare green-linear (cache {})", cache.display()))?;
    bar.finish_and_clear();
    info!(cache = %green.path.display(), candidates = green.candidates().len(), "green-linear ready");
    Ok(GreenLinearModel::new(mesh, green))
}

fn default_cache_dir() -> PathBuf {
    std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))
        .unwrap_or_else(std::env::temp_dir)
        .join("nak")
}

fn serve(args: ServeArgs) -> anyhow::Result<()> {
    let config = serve_config(args)?;
    let engine = Arc::new(build_engine(&config)?);
    let runtime = tokio::runtime::Runtime::new().context("cannot start the async runtime")?;
    runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind(config.listen)
            .await
            .with_context(|| format!("cannot listen on {}", config.listen))?;
        // Scripts and tests read this line to find a port chosen with --listen 127.0.0.1:0.
        info!(address = %listener.local_addr()?, "listening");
        let recorder = start_recorder(&config, &engine)?;
        let intake = serve::Intake {
            max_message_bytes: config.max_message_bytes,
            max_in_flight: config.max_in_flight(),
        };
        serve::run(engine, listener, intake, recorder.clone(), serve::shutdown_signal()).await?;
        if let Some(recorder) = recorder {
            recorder.close().context("the recording was not finished cleanly")?;
        }
        anyhow::Ok(())
    })
}

/// The MCAP recorder, when `--record` is given; its metadata describes the mesh, models and settings.
fn start_recorder(config: &ServeConfig, engine: &Engine) -> anyhow::Result<Option<Arc<Recorder>>> {
    let Some(recording) = config.recording() else {
        return Ok(None);
    };
    let mesh = engine.mesh().clone();
    let models: BTreeMap<&str, &BTreeMap<String, String>> =
        engine.models().map(|m| (m.name.as_str(), &m.metadata)).collect();
    let metadata = BTreeMap::from([
        ("server_version".to_owned(), env!("CARGO_PKG_VERSION").to_owned()),
        ("mesh_name".to_owned(), mesh.config.name.clone()),
        ("mesh_hash".to_owned(), mesh.content_hash.clone()),
        ("mesh_nodes".to_owned(), mesh.node_count().to_string()),
        ("models".to_owned(), serde_json::to_string(&models)?),
        ("config".to_owned(), serde_json::to_string(config)?),
    ]);
    let directory = recording.directory.clone();
    let recorder = Recorder::start(recording, mesh, metadata)
        .with_context(|| format!("cannot record to {}", directory.display()))?;
    Ok(Some(Arc::new(recorder)))
}

fn predict(args: PredictArgs) -> anyhow::Result<()> {
    let config = ServeConfig {
        mesh: args.mesh,
        models: args.models.dirs,
        ort_dylib: args.models.ort_dylib,
        green_linear: args.models.green_linear,
        cache_dir: args.models.cache_dir,
        prior_backend: args.models.prior_backend.unwrap_or_default(),
        ..ServeConfig::default()
    };
    let engine = build_engine(&config)?;
    let grasps = cli::predict::read_grasps(&args.grasps)?;
    let prediction = cli::predict::run(&engine, &args.model, grasps, args.surface_only)?;
    cli::predict::write_npy(&args.out, &prediction.displacements)?;
    print!("{}", cli::predict::summary(&prediction, &args.out));
    Ok(())
}

/// Writes to stdout; a reader that goes away early (`nak mesh info | head`) is not an error.
fn print_or_pipe_closed(f: impl FnOnce(&mut std::io::StdoutLock) -> std::io::Result<()>) -> anyhow::Result<()> {
    match f(&mut std::io::stdout().lock()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        other => Ok(other?),
    }
}
