//! Overload on the quick path: a unary call holds its place under the admission bound from the
//! arrival of its headers until it is answered, whether it is computed on the thread that read it or
//! on the pool, so calls beyond the bound are refused RESOURCE_EXHAUSTED at once instead of queueing
//! in HTTP/2 and tokio. Each case is made certain, not timed: a call whose message the test holds
//! back holds its place for as long as the test wants.

mod common;

use std::convert::Infallible;
use std::time::Duration;

use bytes::Bytes;
use common::models::{coarse, two_graspers};
use common::server::TestServer;
use http_body::Frame;
use http_body_util::{BodyExt, StreamBody};
use hyper_util::rt::TokioExecutor;
use nak::engine::{Engine, Limits};
use nak::proto::v1 as pb;
use nak::proto::v1::deformation_client::DeformationClient;
use nak::serve::Intake;
use nak::wire::grasp_message;
use prost::Message;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;
use tonic::codegen::http;
use tonic::transport::Channel;

fn request() -> pb::PredictRequest {
    pb::PredictRequest {
        grasps: two_graspers(&coarse()).iter().map(grasp_message).collect(),
        ..Default::default()
    }
}

/// A server on the coarse phantom admitting `max_in_flight` calls; every Kelvinlet request is quick.
async fn server(max_in_flight: usize) -> TestServer {
    let intake = Intake {
        max_message_bytes: 1 << 20,
        max_in_flight,
    };
    TestServer::with_intake(Engine::new(coarse(), Limits::default()), intake).await
}

async fn admission(client: &mut DeformationClient<Channel>) -> pb::AdmissionStatus {
    let status = client.get_status(pb::GetStatusRequest {}).await;
    status.ok().and_then(|s| s.into_inner().admission).unwrap_or_default()
}

/// Polls until the server reports `in_flight` places taken.
async fn until_in_flight(client: &mut DeformationClient<Channel>, in_flight: u64) {
    while admission(client).await.in_flight != in_flight {
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// A unary `Predict` call whose headers go out at once and whose message waits for [`Held::send`].
struct Held {
    message: mpsc::Sender<Result<Frame<Bytes>, Infallible>>,
    answer: tokio::task::JoinHandle<Option<String>>,
}

impl Held {
    fn start(server: &TestServer) -> Self {
        let (message, frames) = mpsc::channel(1);
        let http = hyper_util::client::legacy::Client::builder(TokioExecutor::new())
            .http2_only(true)
            .build_http::<StreamBody<ReceiverStream<Result<Frame<Bytes>, Infallible>>>>();
        let call = http::Request::post(format!("http://{}/nak.v1.Deformation/Predict", server.address))
            .header("content-type", "application/grpc")
            .header("te", "trailers")
            .body(StreamBody::new(ReceiverStream::new(frames)))
            .expect("request");
        // The gRPC status of the answer, from its trailers (or its headers, when trailers-only).
        let answer = tokio::spawn(async move {
            let response = http.request(call).await.ok()?;
            let from_headers = response.headers().get("grpc-status").cloned();
            let body = response.into_body().collect().await.ok()?;
            let status = body
                .trailers()
                .and_then(|t| t.get("grpc-status").cloned())
                .or(from_headers)?;
            status.to_str().ok().map(str::to_owned)
        });
        Self { message, answer }
    }

    /// Sends the message (length-prefixed, as gRPC frames it) and ends the request.
    async fn send(self) -> Option<String> {
        let encoded = request().encode_to_vec();
        let mut framed = vec![0u8];
        framed.extend_from_slice(&(encoded.len() as u32).to_be_bytes());
        framed.extend_from_slice(&encoded);
        self.message.send(Ok(Frame::data(Bytes::from(framed)))).await.ok()?;
        drop(self.message);
        self.answer.await.ok().flatten()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_call_holds_its_place_from_arrival_so_the_next_is_refused_at_once_on_the_quick_path() {
    let server = server(1).await;
    let mut client = server.client().await;
    let held = Held::start(&server);
    until_in_flight(&mut client, 1).await;
    // The only place is taken by a call whose message has not even arrived: a quick request is
    // refused, though it would take the runtime thread only a fraction of a millisecond.
    let refused = client.predict(request()).await.expect_err("refused");
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    assert!(refused.message().contains("--max-in-flight"), "{}", refused.message());
    let status = admission(&mut client).await;
    assert_eq!((status.in_flight, status.refused), (1, 1));
    // Its message arrives: it is answered, and its place is free again.
    assert_eq!(held.send().await.as_deref(), Some("0"), "the held call is answered OK");
    until_in_flight(&mut client, 0).await;
    client
        .predict(request())
        .await
        .expect("admitted once the place is free");
    assert_eq!(admission(&mut client).await.refused, 1);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_holds_a_place_only_while_one_of_its_messages_is_answered() {
    let server = server(1).await;
    let mut client = server.client().await;
    let (messages, outgoing) = mpsc::channel(4);
    let mut answers = client
        .predict_stream(ReceiverStream::new(outgoing))
        .await
        .expect("stream")
        .into_inner();
    let mut unary = client.clone();
    for sequence in 0..3 {
        let message = pb::PredictRequest { sequence, ..request() };
        messages.send(message).await.expect("send");
        let answer = answers.message().await.expect("answer").expect("not ended");
        assert!(answer.error.is_none(), "{:?}", answer.error);
        // The stream is open and idle: it holds no place, so a unary call (bound 1) is admitted.
        unary.predict(request()).await.expect("not starved by the open stream");
    }
    drop(messages);
    assert_eq!(admission(&mut client).await.refused, 0);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_a_burst_every_place_is_free_and_only_ok_or_resource_exhausted_came_back() {
    let server = server(2).await;
    let client = server.client().await;
    let calls: Vec<_> = (0..64)
        .map(|_| {
            let mut client = client.clone();
            tokio::spawn(async move { client.predict(request()).await.map(|_| ()) })
        })
        .collect();
    let mut refused = 0;
    for call in calls {
        match call.await.expect("call") {
            Ok(()) => {}
            Err(status) if status.code() == Code::ResourceExhausted => refused += 1,
            Err(status) => panic!("only OK or RESOURCE_EXHAUSTED under a burst: {status:?}"),
        }
    }
    let mut client = client;
    let status = admission(&mut client).await;
    assert_eq!(status.in_flight, 0, "every place is free after the burst");
    assert_eq!(
        status.refused, refused,
        "the server counted each refusal the clients saw"
    );
    server.stop().await;
}
