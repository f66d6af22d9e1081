//! What a deployment relies on, over real sockets: Prometheus metrics counted from real traffic, TLS
//! (certificates made here, at test time) with optional client certificates, the bearer token, and
//! client-side balancing across several servers.

mod common;

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use common::models::{coarse, two_graspers};
use common::server::TestServer;
use nak::bench::{self, BenchConfig, Mode};
use nak::client::{ClientConfig, ClientError, connect};
use nak::engine::{Engine, Limits};
use nak::proto::v1 as pb;
use nak::record::{RecordConfig, Recorder};
use nak::serve::{Intake, Options};
use nak::wire::grasp_message;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tonic::Code;

fn intake() -> Intake {
    Intake {
        max_message_bytes: 1 << 20,
        max_in_flight: 1000,
    }
}

fn request(mesh: &nak::mesh::TetMesh, model: &str) -> pb::PredictRequest {
    pb::PredictRequest {
        model: model.into(),
        grasps: two_graspers(mesh).iter().map(grasp_message).collect(),
        ..Default::default()
    }
}

/// `GET /metrics` over plain HTTP/1.1, as Prometheus scrapes it: the samples by series name.
async fn scrape(address: std::net::SocketAddr) -> BTreeMap<String, f64> {
    let mut stream = tokio::net::TcpStream::connect(address)
        .await
        .expect("connect to metrics");
    stream
        .write_all(b"GET /metrics HTTP/1.1\r\nHost: nak\r\nConnection: close\r\n\r\n")
        .await
        .expect("send");
    let mut response = String::new();
    stream.read_to_string(&mut response).await.expect("read");
    let (head, body) = response.split_once("\r\n\r\n").expect("an HTTP response");
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    assert!(head.contains("application/openmetrics-text"), "{head}");
    assert!(body.trim_end().ends_with("# EOF"), "OpenMetrics text ends with # EOF");
    body.lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
        .filter_map(|l| l.rsplit_once(' '))
        .map(|(series, value)| (series.to_owned(), value.parse().expect("a number")))
        .collect()
}

async fn metrics_listener() -> (tokio::net::TcpListener, std::net::SocketAddr) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
    let address = listener.local_addr().expect("address");
    (listener, address)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_count_real_traffic_by_model_and_status() {
    let mesh = coarse();
    let recordings = tempfile::tempdir().expect("tempdir");
    let recorder = Recorder::start(
        RecordConfig::new(recordings.path().to_owned()),
        mesh.clone(),
        BTreeMap::new(),
    )
    .expect("recorder");
    let (listener, metrics_address) = metrics_listener().await;
    let mut options = Options::new(intake());
    options.metrics = Some(listener);
    options.recorder = Some(Arc::new(recorder));
    let server = TestServer::with_options(Engine::new(mesh.clone(), Limits::default()), options).await;
    let mut client = server.client().await;

    let before = scrape(metrics_address).await;
    assert_eq!(before["nak_models_loaded"], 1.0);
    assert_eq!(before["nak_in_flight"], 0.0);
    assert_eq!(before["nak_max_in_flight"], 1000.0);
    assert!(!before.keys().any(|k| k.starts_with("nak_requests_total")));

    for _ in 0..5 {
        client.predict(request(&mesh, "kelvinlet")).await.expect("answered");
    }
    // The default model is counted under its name.
    client.predict(request(&mesh, "")).await.expect("answered");
    for model in ["no-such-model", "another-typo"] {
        let refused = client.predict(request(&mesh, model)).await.unwrap_err();
        assert_eq!(refused.code(), Code::NotFound);
    }
    let mut bad = request(&mesh, "kelvinlet");
    bad.grasps[0].nodes = vec![u32::MAX];
    assert_eq!(client.predict(bad).await.unwrap_err().code(), Code::InvalidArgument);
    // Stream messages count one by one.
    let messages = tokio_stream::iter(vec![request(&mesh, "kelvinlet"); 3]);
    let mut answers = client.predict_stream(messages).await.expect("stream").into_inner();
    while answers.message().await.expect("answer").is_some() {}

    let mut after = scrape(metrics_address).await;
    for _ in 0..100 {
        if after["nak_recorder_recorded_total"] >= 12.0 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
        after = scrape(metrics_address).await;
    }
    let series = |name: &str| {
        after
            .get(name)
            .copied()
            .unwrap_or_else(|| panic!("no {name} in {after:#?}"))
    };
    assert_eq!(series(r#"nak_requests_total{model="kelvinlet",code="Ok"}"#), 9.0);
    assert_eq!(series(r#"nak_requests_total{model="unknown",code="NotFound"}"#), 2.0);
    assert_eq!(
        series(r#"nak_requests_total{model="kelvinlet",code="InvalidArgument"}"#),
        1.0
    );
    assert_eq!(series(r#"nak_server_latency_seconds_count{model="kelvinlet"}"#), 9.0);
    assert_eq!(series(r#"nak_prior_latency_seconds_count{model="kelvinlet"}"#), 9.0);
    assert!(series(r#"nak_server_latency_seconds_sum{model="kelvinlet"}"#) > 0.0);
    assert!(series(r#"nak_server_latency_seconds_bucket{le="+Inf",model="kelvinlet"}"#) == 9.0);
    // The Kelvinlet has no network stage: no network series.
    assert!(!after.keys().any(|k| k.starts_with("nak_network_latency")));
    assert_eq!(series(r#"nak_model{model="kelvinlet",kind="prior",regime=""}"#), 1.0);
    assert_eq!(series("nak_in_flight"), 0.0);
    assert_eq!(series("nak_admission_refused_total"), 0.0);
    assert_eq!(series("nak_recorder_recorded_total"), 12.0);
    assert_eq!(series("nak_recorder_dropped_total"), 0.0);
    assert_eq!(series("nak_recorder_queue"), 0.0);
    assert_eq!(series("nak_recorder_queue_capacity"), 4096.0);
    server.stop().await;
    // Stopping the server stops its metrics endpoint.
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert!(tokio::net::TcpStream::connect(metrics_address).await.is_err());
}

/// A CA, a server certificate for localhost and 127.0.0.1 signed by it, and a client certificate,
/// written as PEM files.
struct Pki {
    dir: tempfile::TempDir,
}

impl Pki {
    fn new() -> Self {
        use rcgen::{BasicConstraints, CertificateParams, IsCa, Issuer, KeyPair};
        let dir = tempfile::tempdir().expect("tempdir");
        let write = |name: &str, text: String| std::fs::write(dir.path().join(name), text).expect("write");
        let ca_key = KeyPair::generate().expect("key");
        let mut ca_params = CertificateParams::new(Vec::<String>::new()).expect("params");
        ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        let ca = ca_params.self_signed(&ca_key).expect("CA");
        let issuer = Issuer::new(ca_params, ca_key);
        write("ca.pem", ca.pem());
        for (name, names) in [
            ("server", vec!["localhost".to_owned(), "127.0.0.1".to_owned()]),
            ("client", vec!["simulator".to_owned()]),
        ] {
            let key = KeyPair::generate().expect("key");
            let cert = CertificateParams::new(names)
                .expect("params")
                .signed_by(&key, &issuer)
                .expect("sign");
            write(&format!("{name}.pem"), cert.pem());
            write(&format!("{name}-key.pem"), key.serialize_pem());
        }
        write("token", "correct horse battery staple\n".into());
        write("wrong-token", "correct horse battery\n".into());
        Self { dir }
    }

    fn path(&self, name: &str) -> std::path::PathBuf {
        self.dir.path().join(name)
    }

    fn server_tls(&self, client_ca: bool) -> tonic::transport::ServerTlsConfig {
        nak::serve::security::TlsFiles {
            cert: Some(self.path("server.pem")),
            key: Some(self.path("server-key.pem")),
            client_ca: client_ca.then(|| self.path("ca.pem")),
        }
        .server_config()
        .expect("TLS files")
        .expect("TLS on")
    }

    fn client(&self, target: String, token: Option<&str>, client_cert: bool) -> ClientConfig {
        ClientConfig {
            tls_ca: Some(self.path("ca.pem")),
            tls_cert: client_cert.then(|| self.path("client.pem")),
            tls_key: client_cert.then(|| self.path("client-key.pem")),
            auth_token_file: token.map(|t| self.path(t)),
            ..ClientConfig::new(target)
        }
    }
}

async fn tls_server(pki: &Pki, client_ca: bool) -> TestServer {
    tls_server_with_health(pki, client_ca, None).await
}

async fn tls_server_with_health(pki: &Pki, client_ca: bool, health: Option<tokio::net::TcpListener>) -> TestServer {
    let mut options = Options::new(intake());
    options.health = health;
    options.tls = Some(pki.server_tls(client_ca));
    options.auth_token = Some(nak::wire::read_token(&pki.path("token")).expect("token"));
    TestServer::with_options(Engine::new(coarse(), Limits::default()), options).await
}

async fn predict(config: &ClientConfig) -> Result<pb::PredictResponse, tonic::Status> {
    let mut client = connect(config)
        .await
        .map_err(|e| tonic::Status::unavailable(e.to_string()))?;
    client
        .predict(request(&coarse(), "kelvinlet"))
        .await
        .map(|r| r.into_inner())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_and_the_bearer_token_guard_every_call_but_health() {
    let pki = Pki::new();
    let (health_listener, health_address) = metrics_listener().await;
    let server = tls_server_with_health(&pki, false, Some(health_listener)).await;
    let by_name = format!("https://localhost:{}", server.address.port());
    let by_address = format!("https://{}", server.address);

    let answer = predict(&pki.client(by_name.clone(), Some("token"), false))
        .await
        .expect("answered over TLS");
    assert_eq!(answer.node_count as usize, coarse().node_count());
    // The certificate names 127.0.0.1 too.
    predict(&pki.client(by_address.clone(), Some("token"), false))
        .await
        .expect("answered by address");

    for token in [None, Some("wrong-token")] {
        let refused = predict(&pki.client(by_name.clone(), token, false)).await.unwrap_err();
        assert_eq!(refused.code(), Code::Unauthenticated, "{token:?}: {refused:?}");
        // Nothing about what was expected, or how close the guess was.
        assert_eq!(refused.message(), "this server requires a valid bearer token");
    }
    // Reflection needs the token too; health does not (probes carry none).
    let channel = tonic::transport::Endpoint::from_shared(by_name.clone())
        .unwrap()
        .tls_config(
            tonic::transport::ClientTlsConfig::new()
                .ca_certificate(tonic::transport::Certificate::from_pem(
                    std::fs::read(pki.path("ca.pem")).unwrap(),
                ))
                .domain_name("localhost"),
        )
        .unwrap()
        .connect()
        .await
        .expect("TLS connection");
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel.clone());
    let status = health
        .check(tonic_health::pb::HealthCheckRequest {
            service: "nak.v1.Deformation".into(),
        })
        .await
        .expect("health answers without a token")
        .into_inner()
        .status;
    assert_eq!(
        status,
        tonic_health::pb::health_check_response::ServingStatus::Serving as i32
    );
    // The plain health port answers probes that speak no TLS, and serves nothing else.
    let plain = tonic::transport::Endpoint::from_shared(format!("http://{health_address}"))
        .unwrap()
        .connect()
        .await
        .expect("plain health port");
    let serving = tonic_health::pb::health_client::HealthClient::new(plain.clone())
        .check(tonic_health::pb::HealthCheckRequest {
            service: "nak.v1.Deformation".into(),
        })
        .await
        .expect("health over plain HTTP/2")
        .into_inner()
        .status;
    assert_eq!(serving, status);
    let unserved = pb::deformation_client::DeformationClient::new(plain)
        .get_mesh(pb::GetMeshRequest::default())
        .await
        .unwrap_err();
    assert_eq!(unserved.code(), Code::Unimplemented);
    let mut deformation = pb::deformation_client::DeformationClient::new(channel);
    let refused = deformation.list_models(pb::ListModelsRequest {}).await.unwrap_err();
    assert_eq!(refused.code(), Code::Unauthenticated);

    // Plain HTTP/2 to a TLS port gets no answer; TLS checked against the wrong name fails too.
    let plain = format!("http://{}", server.address);
    assert!(predict(&ClientConfig::new(plain)).await.is_err());
    let mut wrong_name = pki.client(by_address, Some("token"), false);
    wrong_name.tls_domain = Some("nak.example.org".into());
    assert!(predict(&wrong_name).await.is_err());
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn client_certificates_are_required_when_a_client_ca_is_given() {
    let pki = Pki::new();
    let server = tls_server(&pki, true).await;
    let target = format!("https://localhost:{}", server.address.port());
    predict(&pki.client(target.clone(), Some("token"), true))
        .await
        .expect("a client with a certificate");
    assert!(predict(&pki.client(target, Some("token"), false)).await.is_err());
    server.stop().await;
}

#[tokio::test]
async fn bad_security_files_are_refused_naming_the_file() {
    let pki = Pki::new();
    let not_pem = pki.path("token");
    let files = nak::serve::security::TlsFiles {
        cert: Some(not_pem.clone()),
        key: Some(pki.path("server-key.pem")),
        client_ca: None,
    };
    let err = files.server_config().unwrap_err().to_string();
    assert!(
        err.contains("holds no PEM certificate") && err.contains(&*not_pem.to_string_lossy()),
        "{err}"
    );
    let missing = Path::new("/nonexistent/token");
    let err = nak::wire::read_token(missing).unwrap_err().to_string();
    assert!(
        err.contains("cannot read bearer token file /nonexistent/token"),
        "{err}"
    );
    let empty = pki.path("empty");
    std::fs::write(&empty, "\n").unwrap();
    let err = nak::wire::read_token(&empty).unwrap_err().to_string();
    assert!(err.contains("is empty"), "{err}");
    let config = ClientConfig {
        tls_cert: Some(pki.path("client.pem")),
        ..pki.client("https://localhost:1".into(), None, false)
    };
    assert!(matches!(connect(&config).await, Err(ClientError::HalfIdentity)));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nak_bench_spreads_requests_over_every_server_it_is_given() {
    let mut servers = Vec::new();
    let mut scrapes = Vec::new();
    for _ in 0..3 {
        let (listener, address) = metrics_listener().await;
        let mut options = Options::new(intake());
        options.metrics = Some(listener);
        servers.push(TestServer::with_options(Engine::new(coarse(), Limits::default()), options).await);
        scrapes.push(address);
    }
    let targets: Vec<String> = servers.iter().map(|s| format!("http://{}", s.address)).collect();
    let config = BenchConfig {
        connection: ClientConfig::new(targets.join(",")),
        model: "kelvinlet".into(),
        mode: Mode::Unary,
        concurrency: 2,
        rate: Some(300.0),
        duration: Duration::from_millis(600),
        warmup: Duration::ZERO,
        graspers: 2,
        seed: 1,
        distinct_requests: 16,
        interval: None,
    };
    let report = bench::run(&config, |_| {}).await.expect("bench");
    assert!(report.errors.is_empty(), "{:?}", report.errors);
    let mut served = Vec::new();
    for address in scrapes {
        let metrics = scrape(address).await;
        served.push(
            metrics
                .get(r#"nak_requests_total{model="kelvinlet",code="Ok"}"#)
                .copied()
                .unwrap_or(0.0),
        );
    }
    let total: f64 = served.iter().sum();
    // Warm-up and measured requests all count at the servers; every server took a fair share.
    assert!(total >= report.requests as f64, "{served:?} vs {}", report.requests);
    for (i, &n) in served.iter().enumerate() {
        assert!(n >= total / 10.0, "server {i} answered {n} of {total}: {served:?}");
    }
    for server in servers {
        server.stop().await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_name_is_resolved_and_its_unreachable_addresses_left_out() {
    // `localhost` resolves to 127.0.0.1 and often ::1; the server listens on the first only.
    let server = TestServer::default().await;
    let mut client = connect(&ClientConfig::new(format!(
        "http://localhost:{}",
        server.address.port()
    )))
    .await
    .expect("connects through the name");
    let mesh = client
        .get_mesh(pb::GetMeshRequest::default())
        .await
        .expect("mesh")
        .into_inner();
    assert_eq!(mesh.node_count as usize, coarse().node_count());
    server.stop().await;
    let err = connect(&ClientConfig::new("http://localhost:1"))
        .await
        .unwrap_err()
        .to_string();
    assert!(err.contains("cannot connect to http://localhost:1"), "{err}");
}
