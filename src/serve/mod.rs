//! `nak serve`: the gRPC server, with health checking, reflection and graceful shutdown.

pub mod admission;
pub mod arrival;
pub mod metrics;
mod priority;
pub mod security;
mod service;
mod status_codes;
pub mod ui;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use serde::Deserialize;
use tokio::net::TcpListener;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::ServerTlsConfig;
use tonic::transport::server::TcpIncoming;
use tracing::{info, warn};

pub use priority::{DEFAULT_COMPUTE_NICENESS, favour_runtime_thread, start_compute_pool};
pub use service::DeformationService;

use crate::engine::{Engine, Limits, Regime};
use crate::prior::PriorBackend;
use crate::proto::v1::FILE_DESCRIPTOR_SET;
use crate::proto::v1::deformation_server::DeformationServer;
use crate::record::{Payload, RecordConfig, Recorder};
use admission::Admission;
use arrival::ArrivalLayer;
use metrics::Metrics;
use security::{RequireToken, SecurityError, TlsFiles};
use tower::Layer;

/// Server settings, from flags or a TOML file (`nak serve --config serve.toml`).
#[derive(Debug, Clone, PartialEq, Deserialize, serde::Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServeConfig {
    /// `--mesh`: a model directory or an .msh file; absent: the embedded phantom liver.
    pub mesh: Option<PathBuf>,
    /// `--regime`: what a request naming no model gets, the most accurate model of this regime
    /// served ([`Engine::default_to_most_accurate`]); absent: the Kelvinlet.
    pub regime: Option<Regime>,
    /// Directories whose subdirectories hold models (`manifest.toml` + `model.onnx`); a `--mesh`
    /// directory is searched too.
    pub models: Vec<PathBuf>,
    /// ONNX Runtime shared library; absent: `ORT_DYLIB_PATH`.
    pub ort_dylib: Option<PathBuf>,
    /// Serve the exact linear model `green-linear`.
    pub green_linear: bool,
    /// Serve `green-tangent`, the hyperelastic model linearized about its gravity-preloaded state.
    pub green_tangent: bool,
    /// Where Green's functions (and the preloaded state) are cached.
    pub cache_dir: Option<PathBuf>,
    /// Where the Kelvinlet field is evaluated: cpu, gpu or auto.
    pub prior_backend: PriorBackend,
    pub listen: SocketAddr,
    /// Serve Prometheus metrics at `http://ADDR/metrics`.
    pub metrics_listen: Option<SocketAddr>,
    /// Serve grpc.health.v1 alone, without TLS, on this address (for the kubelet's gRPC probes).
    pub health_listen: Option<SocketAddr>,
    /// Serve the browser viewer (and gRPC-Web for it) at `http://ADDR/`.
    pub ui: Option<SocketAddr>,
    /// TLS: the server's certificate chain and private key (PEM).
    pub tls_cert: Option<PathBuf>,
    pub tls_key: Option<PathBuf>,
    /// Require client certificates signed by this CA (PEM).
    pub tls_client_ca: Option<PathBuf>,
    /// A file holding the bearer token every call but health checks must present.
    pub auth_token_file: Option<PathBuf>,
    /// Largest grasp displacement accepted, in millimetres.
    pub max_displacement_mm: f64,
    pub max_interaction_points: usize,
    /// Node–point pairs up to which a prior-only request is computed on the connection's thread
    /// instead of the compute pool; 0 sends every request to the pool.
    pub quick_terms: usize,
    /// Largest request message accepted, in bytes; larger ones get RESOURCE_EXHAUSTED.
    pub max_message_bytes: usize,
    /// Most requests admitted to the compute pool at once; more get RESOURCE_EXHAUSTED at once.
    /// 0: [`admission::PER_THREAD`] per compute thread.
    pub max_in_flight: usize,
    /// How much lower than the async runtime's the compute threads' scheduling priority is (Linux
    /// niceness, 0 to 19; 0 leaves them level).
    pub compute_niceness: i32,
    /// Keep idle CPUs polling instead of halting while the server runs ([`crate::cpu_idle`]): each
    /// wake-up of an idle CPU then costs microseconds instead of tens, at the price of idle CPUs
    /// running at full power.
    pub poll_idle_cpus: bool,
    /// Record every exchange to MCAP files in this directory.
    pub record: Option<PathBuf>,
    pub record_payload: Payload,
    pub record_rotate_mb: u64,
    pub record_rotate_minutes: u64,
    pub record_queue: usize,
    pub record_scene_hz: f64,
}

impl Default for ServeConfig {
    fn default() -> Self {
        let limits = Limits::default();
        Self {
            mesh: None,
            regime: None,
            models: Vec::new(),
            ort_dylib: None,
            green_linear: false,
            green_tangent: false,
            cache_dir: None,
            prior_backend: PriorBackend::Cpu,
            listen: SocketAddr::from(([127, 0, 0, 1], 50051)),
            metrics_listen: None,
            health_listen: None,
            ui: None,
            tls_cert: None,
            tls_key: None,
            tls_client_ca: None,
            auth_token_file: None,
            max_displacement_mm: limits.max_displacement_m * 1e3,
            max_interaction_points: limits.max_interaction_points,
            quick_terms: limits.quick_terms,
            max_message_bytes: 1 << 20,
            max_in_flight: 0,
            compute_niceness: DEFAULT_COMPUTE_NICENESS,
            poll_idle_cpus: false,
            record: None,
            record_payload: Payload::Surface,
            record_rotate_mb: 1024,
            record_rotate_minutes: 60,
            record_queue: 4096,
            record_scene_hz: 30.0,
        }
    }
}

impl ServeConfig {
    /// Where models are looked for: a `--mesh` directory (its models are for its default mesh), then
    /// every `--models` directory.
    pub fn model_roots(&self) -> Vec<PathBuf> {
        let mesh_dir = self.mesh.iter().filter(|p| p.is_dir()).cloned();
        mesh_dir.chain(self.models.iter().cloned()).collect()
    }

    /// The recorder's settings, when recording.
    pub fn recording(&self) -> Option<RecordConfig> {
        self.record.as_ref().map(|dir| RecordConfig {
            directory: dir.clone(),
            payload: self.record_payload,
            rotate_bytes: self.record_rotate_mb << 20,
            rotate_after: std::time::Duration::from_secs(60 * self.record_rotate_minutes),
            queue: self.record_queue,
            scene_hz: self.record_scene_hz,
        })
    }

    /// The admission bound: `max_in_flight`, or 4 per compute thread when 0.
    pub fn max_in_flight(&self) -> usize {
        match self.max_in_flight {
            0 => admission::PER_THREAD * rayon::current_num_threads(),
            n => n,
        }
    }

    pub fn tls_files(&self) -> TlsFiles {
        TlsFiles {
            cert: self.tls_cert.clone(),
            key: self.tls_key.clone(),
            client_ca: self.tls_client_ca.clone(),
        }
    }

    pub fn limits(&self) -> Limits {
        Limits {
            max_displacement_m: self.max_displacement_mm * 1e-3,
            max_interaction_points: self.max_interaction_points,
            quick_terms: self.quick_terms,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error("gRPC transport: {0}")]
    Transport(#[from] tonic::transport::Error),
    #[error("server reflection: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
    #[error(transparent)]
    Security(#[from] SecurityError),
}

/// How much one server takes in: the largest message, and the most requests admitted at once.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Intake {
    pub max_message_bytes: usize,
    pub max_in_flight: usize,
}

impl Intake {
    /// The default bound on in-flight requests for this machine, with `max_message_bytes`.
    pub fn with_message_limit(max_message_bytes: usize) -> Self {
        Self {
            max_message_bytes,
            max_in_flight: ServeConfig::default().max_in_flight(),
        }
    }
}

/// What a server is given besides its engine and its gRPC listener.
pub struct Options {
    pub intake: Intake,
    pub recorder: Option<Arc<Recorder>>,
    /// Where `/metrics` is served, if anywhere.
    pub metrics: Option<TcpListener>,
    /// A plain-HTTP/2 port with grpc.health.v1 alone, for probes that speak no TLS (the kubelet's).
    pub health: Option<TcpListener>,
    /// Where the browser viewer and its gRPC-Web access are served, if anywhere.
    pub ui: Option<TcpListener>,
    /// TLS on the gRPC port; `None`: plain HTTP/2.
    pub tls: Option<ServerTlsConfig>,
    /// The bearer token callers must present (health checks excepted).
    pub auth_token: Option<String>,
}

impl Options {
    /// Plain HTTP/2, no recording, no metrics, no token.
    pub fn new(intake: Intake) -> Self {
        Self {
            intake,
            recorder: None,
            metrics: None,
            health: None,
            ui: None,
            tls: None,
            auth_token: None,
        }
    }
}

/// Serves `engine` on `listener` until `shutdown` completes, then drains in-flight calls.
pub async fn run(
    engine: Arc<Engine>,
    listener: TcpListener,
    options: Options,
    shutdown: impl std::future::Future<Output = ()> + Send,
) -> Result<(), ServeError> {
    let Options {
        intake,
        recorder,
        metrics: metrics_listener,
        health: health_listener,
        ui: ui_listener,
        tls,
        auth_token,
    } = options;
    warn_if_exposed(&listener, tls.is_some(), auth_token.is_some());
    let (health_reporter, health_service) = tonic_health::server::health_reporter();
    health_reporter
        .set_serving::<DeformationServer<DeformationService>>()
        .await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    if let Some(recorder) = &recorder {
        tokio::spawn(report_drops(Arc::downgrade(recorder)));
    }
    let admission = Admission::new(intake.max_in_flight);
    let metrics = Arc::new(Metrics::new(engine.clone(), admission.clone(), recorder.clone()));
    let arrival = ArrivalLayer::new(admission.clone(), Some(metrics.clone()));
    let service = DeformationService::new(engine.clone(), recorder, admission, metrics.clone());
    let deformation = DeformationServer::new(service).max_decoding_message_size(intake.max_message_bytes);
    // Health checks stay open: probes (kubelet, load balancers) carry no token. A call without the
    // token is refused before it is admitted, so it takes no place.
    let check_token = RequireToken::new(auth_token.as_deref());
    let deformation = InterceptedService::new(arrival.layer(deformation), check_token.clone());
    let reflection = InterceptedService::new(reflection, check_token);
    // Stopping the gRPC server stops the metrics and health ports too.
    let (stopped, _) = tokio::sync::watch::channel(());
    if let Some(listener) = metrics_listener {
        info!(address = ?listener.local_addr().ok(), "metrics at /metrics");
        let served = metrics::serve(metrics, listener, on_stop(&stopped));
        tokio::spawn(log_failure("the metrics endpoint", served));
    }
    if let Some(listener) = health_listener {
        info!(address = ?listener.local_addr().ok(), "health checks (plain HTTP/2)");
        let served = tonic::transport::Server::builder()
            .add_service(health_service.clone())
            .serve_with_incoming_shutdown(TcpIncoming::from(listener), on_stop(&stopped));
        tokio::spawn(log_failure("the health port", served));
    }
    if let Some(listener) = ui_listener {
        // The viewer's port is plain HTTP/1.1: browsers speak gRPC-Web only over what they can fetch.
        warn_if_exposed(&listener, false, auth_token.is_some());
        info!(address = ?listener.local_addr().ok(), "viewer at http://ADDR/");
        let served = ui::serve(deformation.clone(), listener, on_stop(&stopped));
        tokio::spawn(log_failure("the viewer", served));
    }
    info!(
        max_in_flight = intake.max_in_flight,
        address = ?listener.local_addr().ok(),
        tls = tls.is_some(),
        token = auth_token.is_some(),
        mesh = %engine.mesh().config.name,
        nodes = engine.mesh().node_count(),
        models = ?engine.models().map(|m| m.name.clone()).collect::<Vec<_>>(),
        "serving"
    );
    // Nagle's algorithm would hold back the tail of a response until the client's delayed ACK, 40 ms
    // on Linux; the builder's own nodelay setting does not reach sockets accepted here.
    let incoming = TcpIncoming::from(listener).with_nodelay(Some(true));
    let mut builder = tonic::transport::Server::builder();
    if let Some(tls) = tls {
        builder = builder.tls_config(tls)?;
    }
    builder
        .layer(status_codes::layer())
        .layer(arrival::stamp_layer())
        .add_service(health_service)
        .add_service(reflection)
        .add_service(deformation)
        .serve_with_incoming_shutdown(incoming, shutdown)
        .await?;
    drop(stopped);
    info!("stopped");
    Ok(())
}

/// Completes when the gRPC server has stopped (it drops `stopped`).
fn on_stop(stopped: &tokio::sync::watch::Sender<()>) -> impl std::future::Future<Output = ()> + Send + 'static {
    let mut stop = stopped.subscribe();
    async move {
        let _ = stop.changed().await;
    }
}

/// Runs a side port (metrics, health) to its end, logging why if it fails: it never stops serving.
async fn log_failure<E: std::fmt::Display>(
    what: &'static str,
    served: impl std::future::Future<Output = Result<(), E>>,
) {
    if let Err(e) = served.await {
        tracing::error!(error = %e, "{what} stopped");
    }
}

/// Warns when callers beyond this host could reach a server without TLS: requests, answers and any
/// token would cross the network in clear.
fn warn_if_exposed(listener: &TcpListener, tls: bool, token: bool) {
    let Ok(address) = listener.local_addr() else { return };
    if !tls && !address.ip().is_loopback() {
        warn!(
            %address,
            token,
            "listening beyond loopback without TLS: traffic (and the bearer token, if any) is unencrypted; \
             give --tls-cert and --tls-key"
        );
    }
}

/// Logs, every ten seconds, exchanges the recorder had to drop since the last report.
async fn report_drops(recorder: std::sync::Weak<Recorder>) {
    let mut reported = 0;
    let mut every = tokio::time::interval(std::time::Duration::from_secs(10));
    loop {
        every.tick().await;
        let Some(recorder) = recorder.upgrade() else { return };
        let dropped = recorder.dropped();
        if dropped > reported {
            tracing::warn!(
                dropped = dropped - reported,
                total = dropped,
                "recorder queue full: exchanges not recorded"
            );
            reported = dropped;
        }
    }
}

/// Completes on SIGINT or SIGTERM. On Unix the handlers are installed when this is called, not when
/// the future is first polled: a signal that comes after the server has said it is listening, but
/// before the server polls this, still stops it gracefully instead of killing it.
pub fn shutdown_signal() -> impl std::future::Future<Output = ()> + Send {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let handlers = signal(SignalKind::interrupt()).and_then(|i| Ok((i, signal(SignalKind::terminate())?)));
        async move {
            let (mut interrupt, mut terminate) = match handlers {
                Ok(handlers) => handlers,
                Err(e) => {
                    tracing::warn!(error = %e, "cannot install signal handlers; stop with SIGKILL");
                    return std::future::pending().await;
                }
            };
            tokio::select! {
                _ = interrupt.recv() => info!("SIGINT: shutting down"),
                _ = terminate.recv() => info!("SIGTERM: shutting down"),
            }
        }
    }
    #[cfg(not(unix))]
    async {
        let _ = tokio::signal::ctrl_c().await;
    }
}
