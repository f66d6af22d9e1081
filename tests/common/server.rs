//! A real nak server on an ephemeral loopback port, for tests that talk gRPC to it.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;

use nak::engine::{Engine, Limits};
use nak::mesh::{self, MeshSource};
use nak::proto::v1::deformation_client::DeformationClient;
use nak::serve::{Intake, Options};
use tokio::sync::oneshot;
use tonic::transport::Channel;

pub struct TestServer {
    pub address: SocketAddr,
    pub engine: Arc<Engine>,
    stop: Option<oneshot::Sender<()>>,
    task: Option<tokio::task::JoinHandle<()>>,
}

impl TestServer {
    /// Serves the coarse phantom (fast to load) with the given limits.
    pub async fn start(limits: Limits, max_message_bytes: usize) -> Self {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver/liver-coarse.msh");
        let mesh = Arc::new(mesh::load(&MeshSource::File(path)).expect("coarse phantom"));
        Self::with_engine(Engine::new(mesh, limits), max_message_bytes).await
    }

    /// Serves a prepared engine (with extra models, say).
    pub async fn with_engine(engine: Engine, max_message_bytes: usize) -> Self {
        Self::with_intake(engine, Intake::with_message_limit(max_message_bytes)).await
    }

    /// Serves a prepared engine with the given message and admission limits.
    pub async fn with_intake(engine: Engine, intake: Intake) -> Self {
        Self::with_options(engine, Options::new(intake)).await
    }

    /// Serves a prepared engine with every server option (TLS, token, metrics, recording).
    pub async fn with_options(engine: Engine, options: Options) -> Self {
        let engine = Arc::new(engine);
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let address = listener.local_addr().expect("address");
        let (stop, stopped) = oneshot::channel::<()>();
        let served = engine.clone();
        let task = tokio::spawn(async move {
            let shutdown = async {
                let _ = stopped.await;
            };
            nak::serve::run(served, listener, options, shutdown)
                .await
                .expect("server");
        });
        Self {
            address,
            engine,
            stop: Some(stop),
            task: Some(task),
        }
    }

    pub async fn default() -> Self {
        Self::start(Limits::default(), 1 << 20).await
    }

    pub async fn client(&self) -> DeformationClient<Channel> {
        let channel = Channel::from_shared(format!("http://{}", self.address))
            .expect("uri")
            .connect()
            .await
            .expect("connect");
        DeformationClient::new(channel).max_decoding_message_size(64 << 20)
    }

    pub async fn stop(mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(task) = self.task.take() {
            task.await.expect("server shut down cleanly");
        }
    }
}
