//! `nak serve`: the gRPC server, configured from flags over an optional `serve.toml`, recording to
//! MCAP when asked.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::Context;
use nak::cpu_idle::PollingIdle;
use nak::engine::{Engine, Regime};
use nak::record::{Payload, Recorder};
use nak::serve::{self, ServeConfig};
use nak::wire::read_token;
use tracing::info;

use super::engine::{ModelArgs, build_engine};

#[derive(clap::Args)]
pub struct ServeArgs {
    /// TOML file with any of the settings below, by their long names with underscores (mesh, listen,
    /// metrics_listen, tls_cert, auth_token_file, max_in_flight, record, …). Flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// A model directory (its default mesh) or an .msh file with model.toml beside it
    /// [default: the embedded phantom liver].
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// The regime the organ is served in (nonlinear: hanging under gravity from its fixed area, the
    /// preloaded state surgery sees): a request naming no model gets the most accurate model of that
    /// regime served here (linear: green-linear when served; otherwise the highest held-out DCM in
    /// the models' manifests), and the server does not start when there is none [default: none; such
    /// a request gets the Kelvinlet].
    #[arg(long, value_enum)]
    regime: Option<Regime>,
    /// Address to listen on [default: 127.0.0.1:50051; port 0 picks a free port].
    #[arg(long)]
    listen: Option<SocketAddr>,
    /// Serve Prometheus metrics at http://ADDR/metrics (a port of their own) [default: off].
    #[arg(long, value_name = "ADDR")]
    metrics_listen: Option<SocketAddr>,
    /// Also serve grpc.health.v1 alone on ADDR, in plain HTTP/2: for probes that speak no TLS, such as
    /// the kubelet's [default: off; health is always on the main port too].
    #[arg(long, value_name = "ADDR")]
    health_listen: Option<SocketAddr>,
    /// Serve the viewer at http://ADDR/: the organ in 3D, grasped with the mouse, deforming live
    /// (plain HTTP, gRPC-Web to the same service; a port of its own) [default: off].
    #[arg(long, value_name = "ADDR")]
    ui: Option<SocketAddr>,
    /// TLS: the server's certificate chain (PEM); with --tls-key.
    #[arg(long, value_name = "PEM")]
    tls_cert: Option<PathBuf>,
    /// TLS: the server's private key (PEM); with --tls-cert.
    #[arg(long, value_name = "PEM")]
    tls_key: Option<PathBuf>,
    /// Require client certificates signed by this CA (PEM); needs --tls-cert and --tls-key.
    #[arg(long, value_name = "PEM")]
    tls_client_ca: Option<PathBuf>,
    /// A file holding a bearer token: every call except health checks must send
    /// `authorization: Bearer <token>`, or is refused UNAUTHENTICATED.
    #[arg(long, value_name = "FILE")]
    auth_token_file: Option<PathBuf>,
    /// Largest grasp displacement accepted, millimetres [default: 200].
    #[arg(long)]
    max_displacement_mm: Option<f64>,
    /// Most interaction points (grasped nodes) per request [default: 256].
    #[arg(long)]
    max_interaction_points: Option<usize>,
    /// Prior-only requests over at most this many node–point pairs (nodes answered × interaction
    /// points) are computed on the thread that read them, saving two thread hand-offs; larger ones
    /// and every network go to the compute pool. 0 sends every request to the pool [default: 524288].
    #[arg(long)]
    quick_terms: Option<usize>,
    /// Largest request message, bytes [default: 1048576].
    #[arg(long)]
    max_message_bytes: Option<usize>,
    /// Most requests computed or waiting for the compute pool at once; more are refused at once
    /// with RESOURCE_EXHAUSTED [default: 4 per core].
    #[arg(long)]
    max_in_flight: Option<usize>,
    /// How much lower the compute threads' scheduling priority is than the threads that read
    /// requests and refuse them under overload (Linux niceness, 0 to 19) [default: 5].
    #[arg(long, value_parser = clap::value_parser!(i32).range(0..=19))]
    compute_niceness: Option<i32>,
    /// Keep idle CPUs polling instead of halting while the server runs (a CPU latency QoS request of
    /// 0 µs through /dev/cpu_dma_latency; needs root): a request or answer that wakes an idle CPU
    /// then waits microseconds instead of tens, and idle CPUs run at full power. docs/reports/latency.md
    /// measures both.
    #[arg(long)]
    poll_idle_cpus: bool,
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

pub fn run(args: ServeArgs) -> anyhow::Result<()> {
    let config = serve_config(args)?;
    // Bad certificate or token files fail now, before minutes of model loading.
    let tls = config.tls_files().server_config()?;
    let auth_token = config.auth_token_file.as_deref().map(read_token).transpose()?;
    serve::start_compute_pool(config.compute_niceness).context("cannot start the compute pool")?;
    // Held until the server stops; the kernel drops the request with the file.
    let idle_polling = config.poll_idle_cpus.then(PollingIdle::request).transpose()?;
    if idle_polling.is_some() {
        info!("idle CPUs poll instead of halting while the server runs");
    }
    let engine = Arc::new(build_engine(&config)?);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .on_thread_start(serve::favour_runtime_thread)
        .build()
        .context("cannot start the async runtime")?;
    runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind(config.listen)
            .await
            .with_context(|| format!("cannot listen on {}", config.listen))?;
        // Before "listening": from then on, SIGTERM stops the server gracefully.
        let shutdown = serve::shutdown_signal();
        // Scripts and tests read this line to find a port chosen with --listen 127.0.0.1:0.
        info!(address = %listener.local_addr()?, "listening");
        let recorder = start_recorder(&config, &engine)?;
        let mut options = serve::Options::new(serve::Intake {
            max_message_bytes: config.max_message_bytes,
            max_in_flight: config.max_in_flight(),
        });
        options.recorder = recorder.clone();
        options.tls = tls;
        options.auth_token = auth_token;
        options.metrics = bind(config.metrics_listen, "metrics").await?;
        options.health = bind(config.health_listen, "health checks").await?;
        options.ui = bind(config.ui, "viewer").await?;
        serve::run(engine, listener, options, shutdown).await?;
        if let Some(recorder) = recorder {
            recorder.close().context("the recording was not finished cleanly")?;
        }
        anyhow::Ok(())
    })
}

/// A listener for a side port, when its address is given; logs `<what> listening` with the address
/// (scripts and tests read it to find a port chosen with port 0).
async fn bind(address: Option<SocketAddr>, what: &str) -> anyhow::Result<Option<tokio::net::TcpListener>> {
    let Some(address) = address else { return Ok(None) };
    let listener = tokio::net::TcpListener::bind(address)
        .await
        .with_context(|| format!("cannot listen for {what} on {address}"))?;
    info!(address = %listener.local_addr()?, "{what} listening");
    Ok(Some(listener))
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
    config.regime = args.regime.or(config.regime);
    config.listen = args.listen.unwrap_or(config.listen);
    config.metrics_listen = args.metrics_listen.or(config.metrics_listen);
    config.health_listen = args.health_listen.or(config.health_listen);
    config.ui = args.ui.or(config.ui);
    config.tls_cert = args.tls_cert.or(config.tls_cert);
    config.tls_key = args.tls_key.or(config.tls_key);
    config.tls_client_ca = args.tls_client_ca.or(config.tls_client_ca);
    config.auth_token_file = args.auth_token_file.or(config.auth_token_file);
    config.max_displacement_mm = args.max_displacement_mm.unwrap_or(config.max_displacement_mm);
    config.max_interaction_points = args.max_interaction_points.unwrap_or(config.max_interaction_points);
    config.quick_terms = args.quick_terms.unwrap_or(config.quick_terms);
    config.max_message_bytes = args.max_message_bytes.unwrap_or(config.max_message_bytes);
    config.max_in_flight = args.max_in_flight.unwrap_or(config.max_in_flight);
    config.compute_niceness = args.compute_niceness.unwrap_or(config.compute_niceness);
    config.poll_idle_cpus |= args.poll_idle_cpus;
    anyhow::ensure!(
        (0..=19).contains(&config.compute_niceness),
        "compute_niceness {} is out of range: 0 (level with the runtime) to 19",
        config.compute_niceness
    );
    config.models.extend(args.models.dirs);
    config.green_linear |= args.models.green_linear;
    config.green_tangent |= args.models.green_tangent;
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
