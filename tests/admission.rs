//! Admission control and deadlines over gRPC, with the compute pool held busy by the test (the
//! server runs in this process and shares rayon's global pool), so that what is admitted, refused,
//! expired and abandoned is certain rather than a matter of timing. One test per binary: holding
//! the pool would stall any test beside it.

mod common;

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Barrier};
use std::time::Duration;

use common::models::{coarse, two_graspers};
use common::server::TestServer;
use nak::engine::{Engine, Limits};
use nak::proto::v1 as pb;
use nak::serve::Intake;
use nak::wire::grasp_message;
use tonic::Code;

/// Occupies every thread of rayon's global pool until dropped.
struct PoolHold(Arc<Barrier>);

impl PoolHold {
    fn new() -> Self {
        let threads = rayon::current_num_threads();
        let barrier = Arc::new(Barrier::new(threads + 1));
        let started = Arc::new(AtomicUsize::new(0));
        for _ in 0..threads {
            let (barrier, started) = (barrier.clone(), started.clone());
            rayon::spawn(move || {
                started.fetch_add(1, Ordering::SeqCst);
                barrier.wait();
            });
        }
        while started.load(Ordering::SeqCst) < threads {
            std::thread::yield_now();
        }
        Self(barrier)
    }
}

impl Drop for PoolHold {
    fn drop(&mut self) {
        self.0.wait();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn beyond_the_bound_requests_are_refused_at_once_and_late_or_cancelled_ones_are_not_computed() {
    let mesh = coarse();
    let intake = Intake {
        max_message_bytes: 1 << 20,
        max_in_flight: 3,
    };
    // Every request to the pool, which the test holds: none is quick enough for the connection's thread.
    let limits = Limits {
        quick_terms: 0,
        ..Limits::default()
    };
    let server = TestServer::with_intake(Engine::new(mesh.clone(), limits), intake).await;
    let client = server.client().await;
    let request = pb::PredictRequest {
        grasps: two_graspers(&mesh).iter().map(grasp_message).collect(),
        ..Default::default()
    };
    let status = |mut client: nak::proto::v1::deformation_client::DeformationClient<_>| async move {
        client
            .get_status(pb::GetStatusRequest {})
            .await
            .unwrap()
            .into_inner()
            .admission
            .unwrap()
    };
    let call = |timeout: Option<Duration>| {
        let mut client = client.clone();
        let mut message = tonic::Request::new(request.clone());
        // The header alone, not `set_timeout`: tonic's client would also time the call itself and
        // report its own expiry as CANCELLED, hiding what the server answered.
        if let Some(t) = timeout {
            let header = format!("{}m", t.as_millis()).parse().unwrap();
            message.metadata_mut().insert("grpc-timeout", header);
        }
        tokio::spawn(async move { client.predict(message).await })
    };

    let pool = PoolHold::new();
    // Three places: one call with a 100 ms deadline, one that will be cancelled, one that waits.
    let late = call(Some(Duration::from_millis(100)));
    let cancelled = call(None);
    let patient = call(None);
    while status(client.clone()).await.in_flight < 3 {
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
    // A fourth is refused at once, unary or in a stream; the stream goes on.
    let refused = call(None).await.unwrap().unwrap_err();
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    assert!(refused.message().contains("--max-in-flight"), "{}", refused.message());
    let mut streamed = client
        .clone()
        .predict_stream(tokio_stream::iter(vec![request.clone()]))
        .await
        .unwrap()
        .into_inner();
    let answer = streamed.message().await.unwrap().unwrap();
    assert_eq!(answer.error.unwrap().code, Code::ResourceExhausted as i32);
    // The deadline passes while the pool is busy: DEADLINE_EXCEEDED, from the server.
    let expired = late.await.unwrap().unwrap_err();
    assert_eq!(expired.code(), Code::DeadlineExceeded, "{expired:?}");
    assert!(
        expired.message().contains("nothing was computed"),
        "{}",
        expired.message()
    );
    cancelled.abort();
    assert!(cancelled.await.unwrap_err().is_cancelled());
    tokio::time::sleep(Duration::from_millis(20)).await;
    drop(pool);

    // The patient call is answered; the late and the cancelled ones were never computed.
    let answered = patient.await.unwrap().unwrap().into_inner();
    assert_eq!(answered.interaction_points, 20);
    let mut s = status(client.clone()).await;
    for _ in 0..100 {
        if s.in_flight == 0 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
        s = status(client.clone()).await;
    }
    assert_eq!(
        (s.max_in_flight, s.in_flight, s.refused, s.expired, s.abandoned),
        (3, 0, 2, 1, 2),
        "{s:?}"
    );
    // With the pool free again, requests are admitted as before.
    assert!(call(None).await.unwrap().is_ok());
    server.stop().await;
}
