//! A unary Predict and a streamed round trip over loopback TCP, against an in-process server on the
//! embedded phantom (~9,700 nodes), two graspers of ten nodes (K = 20): what a client sees, including
//! HTTP/2, protobuf and the ~116 kB response.

use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use nak::engine::Engine;
use nak::mesh::{self, MeshSource};
use nak::proto::v1::{Grasp, PredictRequest, Vec3};
use tokio::runtime::Runtime;

fn request(mesh: &nak::mesh::TetMesh) -> PredictRequest {
    let grasp = |set: &str, y: f32| Grasp {
        nodes: mesh.node_sets[set].iter().take(10).copied().collect(),
        displacement: Some(Vec3 { x: 0.01, y, z: 0.0 }),
        ..Default::default()
    };
    PredictRequest {
        grasps: vec![grasp("grasp_03", 0.02), grasp("grasp_08", 0.03)],
        ..Default::default()
    }
}

fn serve(c: &mut Criterion) {
    let mesh = Arc::new(mesh::load(&MeshSource::Embedded).expect("embedded phantom"));
    let message = request(&mesh);
    let engine = Arc::new(Engine::new(mesh, Default::default()));
    // The server gets its own runtime and threads, as it would in its own process.
    let server_runtime = Runtime::new().expect("server runtime");
    let listener = server_runtime
        .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
        .expect("bind");
    let address = listener.local_addr().expect("address");
    server_runtime.spawn(nak::serve::run(
        engine,
        listener,
        nak::serve::Options::new(nak::serve::Intake::with_message_limit(1 << 20)),
        std::future::pending(),
    ));

    let client_runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("client runtime");
    // nak's own client settings (large windows and frames, no Nagle), as `nak bench` uses.
    let mut client = client_runtime
        .block_on(nak::client::connect(&nak::client::ClientConfig::new(format!(
            "http://{address}"
        ))))
        .expect("connect");
    let mut group = c.benchmark_group("loopback");
    group.bench_function("unary_predict_k20", |b| {
        b.to_async(&client_runtime).iter(|| {
            let mut client = client.clone();
            let message = message.clone();
            async move { client.predict(message).await.expect("predict") }
        })
    });
    // One long-lived stream; each iteration sends one request and waits for its answer.
    let (tx, rx) = tokio::sync::mpsc::channel::<PredictRequest>(1);
    let mut answers = client_runtime
        .block_on(client.predict_stream(tokio_stream::wrappers::ReceiverStream::new(rx)))
        .expect("stream")
        .into_inner();
    group.bench_function("stream_round_trip_k20", |b| {
        b.iter(|| {
            client_runtime.block_on(async {
                tx.send(message.clone()).await.expect("send");
                answers.message().await.expect("answer").expect("open stream")
            })
        })
    });
    group.finish();
}

criterion_group!(benches, serve);
criterion_main!(benches);
