//! The `nak` binary: serve (with graceful shutdown on SIGTERM), predict, mesh info and refine.

mod common;

use std::path::Path;

use common::process::{ServeProcess, nak};
use nak::proto::v1::deformation_client::DeformationClient;
use nak::proto::v1::{Grasp, PredictRequest, Vec3};

fn repo(path: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

#[test]
fn serve_answers_on_the_embedded_phantom_and_stops_cleanly_on_sigterm() {
    let mut serve = nak();
    serve.arg("serve");
    let server = ServeProcess::start(serve);
    let address = server.address.clone();
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let response = runtime.block_on(async {
        let mut client = DeformationClient::connect(format!("http://{address}")).await.unwrap();
        let mesh = client
            .get_mesh(nak::proto::v1::GetMeshRequest::default())
            .await
            .unwrap()
            .into_inner();
        assert_eq!(mesh.name, "phantom-liver");
        let node = mesh.node_sets.iter().find(|s| s.name == "grasp_04").unwrap().nodes[0];
        client.predict(lift("", node)).await.unwrap().into_inner()
    });
    assert!(response.node_count > 9_500);
    let (exit, rest) = server.stop();
    assert!(exit.success(), "exit {exit:?}; log: {rest:?}");
    assert!(rest.iter().any(|l| l.contains("SIGTERM")), "{rest:?}");
    assert!(rest.iter().any(|l| l.contains("\"stopped\"")), "{rest:?}");
}

/// A grasp of `node` by 2 cm upwards, for the model `model` (empty: the server's default).
fn lift(model: &str, node: u32) -> PredictRequest {
    PredictRequest {
        model: model.into(),
        grasps: vec![Grasp {
            nodes: vec![node],
            displacement: Some(Vec3 {
                x: 0.0,
                y: 0.02,
                z: 0.0,
            }),
            ..Default::default()
        }],
        ..Default::default()
    }
}

#[test]
fn serve_regime_nonlinear_answers_a_request_naming_no_model_with_the_most_accurate_nonlinear_network() {
    common::models::ort();
    let mut serve = nak();
    serve.args(["serve", "--regime", "nonlinear"]);
    let server = ServeProcess::start(serve);
    let address = server.address.clone();
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let mut client = DeformationClient::connect(format!("http://{address}")).await.unwrap();
        let listed = client
            .list_models(nak::proto::v1::ListModelsRequest {})
            .await
            .unwrap()
            .into_inner();
        let dcm = |m: &nak::proto::v1::ModelInfo| m.metadata.get("metrics.dcm_combined")?.parse::<f64>().ok();
        let best = listed
            .models
            .iter()
            .filter(|m| m.regime == "nonlinear")
            .filter_map(|m| Some((dcm(m)?, m.name.clone())))
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .expect("the phantom ships scored nonlinear networks")
            .1;
        assert_eq!(listed.default_model, best);
        let mesh = client
            .get_mesh(nak::proto::v1::GetMeshRequest::default())
            .await
            .unwrap()
            .into_inner();
        let node = mesh.node_sets.iter().find(|s| s.name == "grasp_04").unwrap().nodes[0];
        let unnamed = client.predict(lift("", node)).await.unwrap().into_inner();
        let named = client.predict(lift(&best, node)).await.unwrap().into_inner();
        assert_eq!(unnamed.model, best);
        assert_eq!(unnamed.displacements, named.displacements);
    });
    let (exit, rest) = server.stop();
    assert!(exit.success(), "exit {exit:?}; log: {rest:?}");
}

#[test]
fn serve_regime_with_no_model_of_that_regime_does_not_start_and_says_what_is_served() {
    let output = nak()
        .args(["serve", "--listen", "127.0.0.1:0", "--regime", "nonlinear", "--mesh"])
        .arg(repo("models/phantom-liver/liver-coarse.msh"))
        .output()
        .unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("--regime nonlinear")
            && stderr.contains("no nonlinear model")
            && stderr.contains("served: kelvinlet"),
        "{stderr}"
    );
}

#[test]
fn predict_writes_a_float32_npy_of_every_node() {
    let dir = tempfile::tempdir().unwrap();
    let grasps = dir.path().join("grasps.json");
    std::fs::write(
        &grasps,
        r#"{"grasps":[{"point":[-0.06,-0.05,0.04],"radius":0.008,"displacement":[0.01,0.02,0.0]},
                      {"point":[0.05,-0.01,0.03],"radius":0,"displacement":[0.0,0.03,0.0]}]}"#,
    )
    .unwrap();
    let out = dir.path().join("u.npy");
    let output = nak()
        .arg("predict")
        .arg("--mesh")
        .arg(repo("models/phantom-liver/liver-coarse.msh"))
        .args(["--model", "kelvinlet", "--grasps"])
        .arg(&grasps)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let bytes = std::fs::read(&out).unwrap();
    let npy = npyz::NpyFile::new(&bytes[..]).unwrap();
    assert_eq!(npy.shape(), &[2052, 3]);
    let values: Vec<f32> = npy.into_vec().unwrap();
    let largest = values
        .chunks(3)
        .map(|u| (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt())
        .fold(0.0, f32::max);
    // The grasped nodes move by their displacements; nothing moves much further.
    assert!((0.029..0.031).contains(&largest), "{largest}");
}

#[test]
fn predict_refuses_bad_grasps_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    let grasps = dir.path().join("grasps.json");
    std::fs::write(
        &grasps,
        r#"{"grasps":[{"nodes":[99999999],"displacement":[0,0.01,0]}]}"#,
    )
    .unwrap();
    let output = nak()
        .args(["predict", "--grasps"])
        .arg(&grasps)
        .arg("--out")
        .arg(dir.path().join("u.npy"))
        .output()
        .unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("holds node 99999999"), "{stderr}");
}

#[test]
fn mesh_info_summarizes_and_refuses_missing_files() {
    let output = nak()
        .args(["mesh", "info"])
        .arg(repo("models/phantom-liver"))
        .output()
        .unwrap();
    assert!(output.status.success());
    let text = String::from_utf8_lossy(&output.stdout);
    for expected in [
        "nodes       9701",
        "closed and manifold",
        "liver",
        "gallbladder",
        "ducts",
        "grasp_10",
        "dihedral",
    ] {
        assert!(text.contains(expected), "{expected} missing from:\n{text}");
    }
    let output = nak().args(["mesh", "info", "no/such.msh"]).output().unwrap();
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("no/such.msh"));
}

#[test]
fn mesh_refine_writes_a_finer_mesh_that_loads_with_its_configuration() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("finer/liver.vtu");
    let output = nak()
        .args(["mesh", "refine"])
        .arg(repo("models/phantom-liver/liver-coarse.msh"))
        .arg(&out)
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let said = String::from_utf8_lossy(&output.stdout);
    assert!(said.contains("model.toml written"), "{said}");
    let config = std::fs::read_to_string(dir.path().join("finer/model.toml")).unwrap();
    assert!(config.contains("default = \"liver.vtu\""), "{config}");
    // The directory serves as a mesh source now, and the mesh is the coarse one split once.
    let info = nak()
        .args(["mesh", "info"])
        .arg(dir.path().join("finer"))
        .output()
        .unwrap();
    assert!(info.status.success(), "{}", String::from_utf8_lossy(&info.stderr));
    let text = String::from_utf8_lossy(&info.stdout);
    let coarse = nak()
        .args(["mesh", "info"])
        .arg(repo("models/phantom-liver/liver-coarse.msh"))
        .output()
        .unwrap();
    let tets = |text: &str| -> usize {
        let line = text.lines().find(|l| l.starts_with("tetrahedra")).unwrap();
        line.split_whitespace().nth(1).unwrap().parse().unwrap()
    };
    assert_eq!(tets(&text), 8 * tets(&String::from_utf8_lossy(&coarse.stdout)));
    let refused = nak()
        .args(["mesh", "refine", "embedded"])
        .arg(dir.path().join("liver.msh"))
        .output()
        .unwrap();
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("name it .vtu or .vtk"));
}

#[test]
fn a_serve_config_file_sets_the_listen_address_and_limits() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("serve.toml");
    std::fs::write(
        &config,
        "listen = \"127.0.0.1:0\"\nmax_displacement_mm = 50.0\nbogus = 1\n",
    )
    .unwrap();
    let output = nak().args(["serve", "--config"]).arg(&config).output().unwrap();
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("unknown field `bogus`"));
}

#[test]
fn compute_niceness_outside_what_the_kernel_allows_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("serve.toml");
    std::fs::write(&config, "listen = \"127.0.0.1:0\"\ncompute_niceness = 25\n").unwrap();
    let output = nak().args(["serve", "--config"]).arg(&config).output().unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("compute_niceness 25 is out of range"), "{stderr}");

    let output = nak().args(["serve", "--compute-niceness", "20"]).output().unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("--compute-niceness") && stderr.contains("0..=19"),
        "{stderr}"
    );
}

#[test]
fn predict_serves_onnx_models_too() {
    assert!(
        std::env::var_os("ORT_DYLIB_PATH").is_some(),
        "ORT_DYLIB_PATH is not set (scripts/test sets it)"
    );
    let dir = tempfile::tempdir().unwrap();
    let grasps = dir.path().join("grasps.json");
    std::fs::write(
        &grasps,
        r#"{"grasps":[{"point":[0.05,-0.01,0.03],"radius":0,"displacement":[0.0,0.03,0.0]}]}"#,
    )
    .unwrap();
    let mut fields = Vec::new();
    for model in ["kelvinlet", "pointnet-residual"] {
        let out = dir.path().join(format!("{model}.npy"));
        let output = nak()
            .arg("predict")
            .arg("--mesh")
            .arg(repo("models/phantom-liver/liver-coarse.msh"))
            .arg("--models")
            .arg(repo("tests/models/phantom-liver-coarse"))
            .args(["--model", model, "--grasps"])
            .arg(&grasps)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
        let bytes = std::fs::read(&out).unwrap();
        let values: Vec<f32> = npyz::NpyFile::new(&bytes[..]).unwrap().into_vec().unwrap();
        fields.push(values);
    }
    // The residual network moves the field away from the prior, by millimetres.
    let diff = fields[0]
        .iter()
        .zip(&fields[1])
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(diff > 1e-5 && diff < 0.02, "{diff}");
}

#[test]
fn serve_checks_the_token_exports_metrics_and_warns_when_exposed_without_tls() {
    let dir = tempfile::tempdir().unwrap();
    let token = dir.path().join("token");
    std::fs::write(&token, "s3cret\n").unwrap();
    let mut serve = nak();
    serve
        .args(["serve", "--metrics-listen", "127.0.0.1:0", "--auth-token-file"])
        .arg(&token);
    let mut server = ServeProcess::start_on(serve, "0.0.0.0:0");
    let port = server.address.rsplit_once(':').unwrap().1.to_owned();
    let metrics = server
        .wait_for(std::time::Duration::from_secs(10), |r| {
            r["fields"]["message"] == "metrics listening"
        })
        .and_then(|r| r["fields"]["address"].as_str().map(str::to_owned))
        .expect("the metrics address is logged");
    let warned = server.wait_for(std::time::Duration::from_secs(10), |r| {
        r["level"] == "WARN"
            && r["fields"]["message"]
                .as_str()
                .is_some_and(|m| m.contains("without TLS"))
    });
    assert!(warned.is_some(), "{:#?}", server.log());

    let report = dir.path().join("bench.json");
    let bench = |with_token: bool| {
        let mut bench = nak();
        bench.args(["bench", "--target", &format!("http://127.0.0.1:{port}")]);
        bench.args(["--duration", "300ms", "--warmup", "0s", "--concurrency", "1"]);
        bench.arg("--output").arg(&report);
        if with_token {
            bench.arg("--auth-token-file").arg(&token);
        }
        bench.output().unwrap()
    };
    let refused = bench(false);
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("requires a valid bearer token"), "{stderr}");
    let answered = bench(true);
    assert!(
        answered.status.success(),
        "{}",
        String::from_utf8_lossy(&answered.stderr)
    );

    let mut stream = std::net::TcpStream::connect(&metrics).unwrap();
    std::io::Write::write_all(&mut stream, b"GET /metrics HTTP/1.0\r\n\r\n").unwrap();
    let mut text = String::new();
    std::io::Read::read_to_string(&mut stream, &mut text).unwrap();
    let answered: f64 = text
        .lines()
        .find_map(|l| l.strip_prefix(r#"nak_requests_total{model="kelvinlet",code="Ok"} "#))
        .unwrap_or_else(|| panic!("{text}"))
        .parse()
        .unwrap();
    // Every answer the load test counted was counted by the server too (it may have answered one
    // more, after the measured window closed); how many fit in 300 ms depends on the machine's load.
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    let counted = report["requests"].as_u64().unwrap();
    assert!(
        counted > 0 && report["errors"].as_object().unwrap().is_empty(),
        "{report}"
    );
    assert!(answered >= counted as f64, "{counted} answers measured; {text}");
    let (exit, rest) = server.stop();
    assert!(exit.success(), "exit {exit:?}; log: {rest:?}");
}

#[test]
fn poll_idle_cpus_holds_a_zero_latency_request_while_the_server_runs() {
    let device = nak::cpu_idle::CPU_LATENCY_DEVICE;
    let permitted = std::fs::OpenOptions::new().write(true).open(device).is_ok();
    if !permitted {
        // Without the right to ask, the server must say so and not start.
        let output = nak()
            .args(["serve", "--listen", "127.0.0.1:0", "--poll-idle-cpus"])
            .output()
            .unwrap();
        assert!(!output.status.success());
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(stderr.contains(device), "{stderr}");
        return;
    }
    let bound_before = nak::cpu_idle::current_bound_us().unwrap();
    let mut serve = nak();
    serve.args(["serve", "--poll-idle-cpus"]);
    let server = ServeProcess::start(serve);
    // Logged before the engine loads, so among the lines read while waiting for "listening".
    let announced = server
        .log()
        .iter()
        .any(|l| l.contains("idle CPUs poll instead of halting"));
    assert!(announced, "{:#?}", server.log());
    assert_eq!(nak::cpu_idle::current_bound_us().unwrap(), 0);
    let (exit, rest) = server.stop();
    assert!(exit.success(), "exit {exit:?}; log: {rest:?}");
    // The kernel drops the request with the process (unless someone else held one already).
    if bound_before != 0 {
        assert_eq!(nak::cpu_idle::current_bound_us().unwrap(), bound_before);
    }
}
