//! `nak bench` against a real server: every mode completes, counts add up, errors are attributed.
//! Nothing here asserts a speed; speed is what the tool reports.

mod common;

use std::time::Duration;

use common::models::coarse;
use common::server::TestServer;
use nak::bench::{self, BenchConfig, Mode};
use nak::client::ClientConfig;
use nak::engine::{Engine, Limits};
use nak::serve::Intake;

/// A server that admits every request: these tests count what the tool sends and receives, on a
/// debug build that a busy machine may slow past the default admission bound.
async fn unbounded_server() -> TestServer {
    let intake = Intake {
        max_message_bytes: 1 << 20,
        max_in_flight: 100_000,
    };
    TestServer::with_intake(Engine::new(coarse(), Limits::default()), intake).await
}

fn config(server: &TestServer, mode: Mode, rate: Option<f64>) -> BenchConfig {
    BenchConfig {
        connection: ClientConfig::new(format!("http://{}", server.address)),
        model: "kelvinlet".into(),
        mode,
        concurrency: 2,
        rate,
        duration: Duration::from_millis(600),
        warmup: Duration::from_millis(100),
        graspers: 2,
        seed: 3,
        distinct_requests: 64,
        interval: None,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn open_loop_sends_exactly_the_offered_load_in_both_modes() {
    let server = unbounded_server().await;
    for mode in [Mode::Unary, Mode::Stream] {
        let report = bench::run(&config(&server, mode, Some(200.0)), |_| {}).await.unwrap();
        // 200/s over 0.6 s: requests due in the measured window, each answered.
        assert!((118..=122).contains(&report.requests), "{mode:?}: {}", report.requests);
        assert!(report.errors.is_empty(), "{:?}", report.errors);
        let l = report.latency_us;
        assert!(l.p50 <= l.p90 && l.p90 <= l.p99 && l.p99 <= l.p999 && l.p999 <= l.max);
        assert!(report.server_us.p50 > 0.0);
        // Every request was handed to the client after it was due and before it was answered.
        let g = report.generator_us;
        assert!(
            g.p50 >= 1.0 && g.max <= l.max,
            "{mode:?}: generator {g:?}, latency {l:?}"
        );
        assert!(report.server_queue_us.p50 <= report.server_us.p50);
        // The prior is part of the server's time; this server's is on the CPU.
        let prior = report.server_prior_us.p50;
        assert!(prior > 0.0 && prior <= report.server_us.p50, "{prior}");
        assert!(report.gpu.is_none());
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn closed_loop_runs_for_the_duration_in_both_modes() {
    let server = unbounded_server().await;
    for mode in [Mode::Unary, Mode::Stream] {
        let ticks = std::sync::atomic::AtomicUsize::new(0);
        let report = bench::run(&config(&server, mode, None), |_| {
            ticks.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        })
        .await
        .unwrap();
        assert!(report.requests > 10, "{mode:?}: {}", report.requests);
        let ticks = ticks.into_inner();
        assert!(ticks >= 2, "progress was reported {ticks} times");
        assert_eq!(report.rate_rps, None);
        let json: serde_json::Value = serde_json::to_value(&report).unwrap();
        for key in ["p50", "p90", "p99", "p999", "max"] {
            assert!(json["latency_us"][key].is_number(), "{key}");
        }
        assert!(json["throughput_rps"].as_f64().unwrap() > 0.0);
        if cfg!(target_os = "linux") {
            let steal = json["steal_percent"].as_f64().expect("steal time, from /proc/stat");
            assert!((0.0..=100.0).contains(&steal), "{steal}");
            let cpu = json["client_cpu_us"]
                .as_f64()
                .expect("this process's CPU time per request");
            assert!(cpu > 0.0, "{cpu}");
        }
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn errors_are_counted_by_status_code() {
    let server = unbounded_server().await;
    for mode in [Mode::Unary, Mode::Stream] {
        let mut c = config(&server, mode, Some(100.0));
        c.model = "no-such-model".into();
        let report = bench::run(&c, |_| {}).await.unwrap();
        assert_eq!(
            report.errors.get("NOT_FOUND").copied(),
            Some(report.requests),
            "{mode:?}: {:?}",
            report.errors
        );
        assert!(report.requests > 50);
        // What the server said comes with the count, in the JSON and the table.
        let example = &report.error_examples["NOT_FOUND"];
        assert!(example.contains("unknown model \"no-such-model\""), "{example}");
        assert!(report.table().contains("NOT_FOUND"), "{}", report.table());
        // Every outcome was a refusal: timed as such, and nothing as an answer.
        let refused = report.refused_us.unwrap();
        assert_eq!(refused.max, report.latency_us.max);
        assert_eq!(report.answered_us.max, 0.0);
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn intervals_split_the_measured_window() {
    let server = unbounded_server().await;
    let mut c = config(&server, Mode::Unary, Some(200.0));
    c.interval = Some(Duration::from_millis(200));
    let report = bench::run(&c, |_| {}).await.unwrap();
    let starts: Vec<f64> = report.intervals.iter().map(|i| i.start_s).collect();
    assert_eq!(starts, [0.0, 0.2, 0.4]);
    assert_eq!(
        report.intervals.iter().map(|i| i.requests).sum::<u64>(),
        report.requests
    );
    assert!(
        report
            .intervals
            .iter()
            .all(|i| i.refused == 0 && i.latency_us.p99 > 0.0)
    );
    assert!(report.refused_us.is_none());
    server.stop().await;
}

#[tokio::test]
async fn an_unreachable_target_is_a_clear_error() {
    let c = BenchConfig {
        connection: ClientConfig::new("http://127.0.0.1:1"),
        model: "kelvinlet".into(),
        mode: Mode::Unary,
        concurrency: 1,
        rate: None,
        duration: Duration::from_millis(100),
        warmup: Duration::ZERO,
        graspers: 1,
        seed: 0,
        distinct_requests: 1,
        interval: None,
    };
    let err = bench::run(&c, |_| {}).await.unwrap_err().to_string();
    assert!(err.contains("cannot connect to http://127.0.0.1:1"), "{err}");
}
