//! Faults around the server, not in the requests: a disk that fills under the recorder, a model that
//! runs far longer than its callers wait, a corrupt model file at start. In each, nak keeps serving
//! and says what went wrong, and where.

mod common;

use std::path::Path;
use std::process::Command;
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::models::{coarse, copy_model, ort, test_models, two_graspers};
use common::process::{ServeProcess, nak};
use common::server::TestServer;
use hyper_util::client::legacy::connect::HttpConnector;
use hyper_util::rt::TokioExecutor;
use nak::engine::{Engine, Limits};
use nak::model;
use nak::proto::v1 as pb;
use nak::proto::v1::deformation_client::DeformationClient;
use tonic::Code;
use tonic::transport::Channel;

fn request(model: &str) -> pb::PredictRequest {
    pb::PredictRequest {
        model: model.into(),
        grasps: two_graspers(&coarse()).iter().map(nak::wire::grasp_message).collect(),
        ..Default::default()
    }
}

/// A client that sends a call's `grpc-timeout` without also timing the call itself, as tonic's
/// `Channel` does from before sending: on a busy machine its CANCELLED could come first, and only the
/// server's answer is under test.
fn untimed_client(
    address: std::net::SocketAddr,
) -> DeformationClient<hyper_util::client::legacy::Client<HttpConnector, tonic::body::Body>> {
    let http = hyper_util::client::legacy::Client::builder(TokioExecutor::new())
        .http2_only(true)
        .build_http();
    DeformationClient::with_origin(http, format!("http://{address}").parse().unwrap())
}

async fn status(client: &mut DeformationClient<Channel>) -> pb::ServerStatus {
    client.get_status(pb::GetStatusRequest {}).await.unwrap().into_inner()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_model_that_runs_long_is_answered_at_the_deadline_and_others_are_served_meanwhile() {
    let mesh = coarse();
    let mut engine = Engine::new(mesh.clone(), Limits::default());
    for m in model::load_all(&test_models().join("faulty/slow"), &mesh, ort()).unwrap() {
        engine.add_model(Arc::new(m));
    }
    let server = TestServer::with_engine(engine, 1 << 20).await;
    let mut client = server.client().await;

    let mut slow = tonic::Request::new(request("slow"));
    slow.metadata_mut().insert("grpc-timeout", "300m".parse().unwrap());
    let asked = Instant::now();
    let refused = untimed_client(server.address).predict(slow).await.unwrap_err();
    let waited = asked.elapsed();
    assert_eq!(refused.code(), Code::DeadlineExceeded, "{refused:?}");
    assert!(refused.message().contains("still computing"), "{}", refused.message());
    // The answer came at the deadline, not when the model finished (seconds later).
    assert!(waited < Duration::from_secs(2), "answered after {waited:?}");

    // The slow computation holds one compute thread and one place; the Kelvinlet is served beside it.
    assert_eq!(status(&mut client).await.admission.unwrap().in_flight, 1);
    let answer = client.predict(request("kelvinlet")).await.unwrap().into_inner();
    assert_eq!(answer.node_count as usize, mesh.node_count());

    // When the model finishes, its place is freed.
    let freed = Instant::now();
    loop {
        let admission = status(&mut client).await.admission.unwrap();
        if admission.in_flight == 0 {
            assert_eq!(admission.expired, 1);
            break;
        }
        assert!(
            freed.elapsed() < Duration::from_secs(300),
            "the slow model never finished"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    server.stop().await;
}

fn client_for(address: &str) -> (tokio::runtime::Runtime, DeformationClient<Channel>) {
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let client = runtime
        .block_on(DeformationClient::connect(format!("http://{address}")))
        .unwrap()
        .max_decoding_message_size(64 << 20);
    (runtime, client)
}

#[test]
fn a_corrupt_model_file_at_start_is_refused_by_name_and_the_others_are_served() {
    let (_root, good) = copy_model("mlp-residual");
    let models = good.parent().unwrap();
    let broken = models.join("broken");
    std::fs::create_dir(&broken).unwrap();
    std::fs::copy(good.join("manifest.toml"), broken.join("manifest.toml")).unwrap();
    let manifest = std::fs::read_to_string(broken.join("manifest.toml")).unwrap();
    std::fs::write(
        broken.join("manifest.toml"),
        manifest.replace("name = \"mlp-residual\"", "name = \"broken\""),
    )
    .unwrap();
    // Half of a real model: what an interrupted copy leaves.
    let onnx = std::fs::read(good.join("model.onnx")).unwrap();
    std::fs::write(broken.join("model.onnx"), &onnx[..onnx.len() / 2]).unwrap();

    let mut serve = nak();
    serve
        .args(["serve", "--mesh"])
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver/liver-coarse.msh"))
        .arg("--models")
        .arg(models);
    let server = ServeProcess::start(serve);
    let (runtime, mut client) = client_for(&server.address);
    let (listed, status) = runtime.block_on(async {
        let listed = client.list_models(pb::ListModelsRequest {}).await.unwrap().into_inner();
        (listed, status(&mut client).await)
    });
    let names: Vec<&str> = listed.models.iter().map(|m| m.name.as_str()).collect();
    assert!(
        names.contains(&"mlp-residual") && !names.contains(&"broken"),
        "{names:?}"
    );
    let [refused] = &status.refused_models[..] else {
        panic!("{:?}", status.refused_models)
    };
    let file = broken.join("model.onnx").display().to_string();
    assert!(refused.origin.contains(&file), "{refused:?}");
    let (exit, log) = server.stop();
    assert!(exit.success());
    assert!(
        log.iter().any(|l| l.contains("model refused") && l.contains(&file)),
        "{log:#?}"
    );
}

/// `nak serve` recording into a 512 KiB tmpfs of its own: a private mount namespace (`unshare`,
/// util-linux) so that nothing is left mounted, whatever happens to the test.
fn serve_recording_on_a_small_disk(dir: &Path) -> Command {
    let script = format!(
        "mount -t tmpfs -o size=512k nak-test {dir} && exec \"$0\" \"$@\"",
        dir = dir.display()
    );
    let mut c = Command::new("unshare");
    c.args(["--mount", "--propagation", "private", "sh", "-c", &script])
        .arg(env!("CARGO_BIN_EXE_nak"))
        .args(["serve", "--record-payload", "full", "--record-scene-hz", "0", "--mesh"])
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver/liver-coarse.msh"))
        .arg("--record")
        .arg(dir)
        .env("NO_COLOR", "1");
    c
}

#[test]
fn a_full_disk_stops_the_recording_and_serving_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let mut server = ServeProcess::start(serve_recording_on_a_small_disk(dir.path()));
    let (runtime, mut client) = client_for(&server.address);
    // Each answer is ~25 kB of displacements, each different (identical ones would compress to
    // nothing): 80 of them fill 512 KiB several times over.
    let during = runtime.block_on(async {
        for i in 0..80 {
            let mut message = request("kelvinlet");
            for grasp in &mut message.grasps {
                let u = grasp.displacement.as_mut().unwrap();
                u.x += 1e-4 * i as f32;
                u.z -= 1e-4 * i as f32;
            }
            let answer = client.predict(message).await.unwrap().into_inner();
            assert!(answer.node_count > 2000);
        }
        status(&mut client).await
    });
    let stopped = server.wait_for(Duration::from_secs(10), |r| {
        r["fields"]["message"] == "recording stopped; serving continues without it"
    });
    let stopped = stopped.unwrap_or_else(|| panic!("no log line says the recording stopped: {:#?}", server.log()));
    assert!(
        stopped["fields"]["error"].as_str().unwrap().contains("No space left"),
        "{stopped}"
    );
    // The writer may stop a moment after the answers; ask again once its log line is out.
    let recorder = runtime.block_on(async {
        let answer = client.predict(request("kelvinlet")).await.unwrap().into_inner();
        assert!(answer.node_count > 2000);
        status(&mut client).await.recorder.unwrap()
    });
    assert!(during.recorder.unwrap().enabled);
    assert!(recorder.error.contains("No space left"), "{recorder:?}");
    assert!(recorder.dropped >= 1, "{recorder:?}");
    assert!(recorder.recorded + recorder.dropped == 81, "{recorder:?}");
    let (exit, _) = server.stop();
    assert!(exit.success());
}
