//! The `nak.v1.Deformation` service over an [`Engine`].

use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Instant, SystemTime};

use tokio_stream::{Stream, StreamExt};
use tonic::{Code, Request, Response, Status, Streaming};
use tracing::{debug, warn};

use super::admission::{self, Admission};
use super::arrival::{self, Admitted};
use super::metrics::Metrics;
use super::status_codes::TOO_LARGE;
use crate::engine::{self, Engine, EngineError, Prediction, Prepared};
use crate::proto::v1 as pb;
use crate::proto::v1::deformation_server::Deformation;
use crate::record::{Exchange, Recorder};
use crate::wire::convert;

#[derive(Clone)]
pub struct DeformationService {
    engine: Arc<Engine>,
    recorder: Option<Arc<Recorder>>,
    admission: Arc<Admission>,
    metrics: Arc<Metrics>,
    started: Instant,
    /// GetMesh's answer, built once: the mesh never changes while serving.
    mesh: Arc<pb::Mesh>,
    /// Quick requests are computed on the thread that read them while at most this many requests
    /// hold places: one runtime thread fewer than the runtime has (at least one).
    inline_while: usize,
}

impl DeformationService {
    pub fn new(
        engine: Arc<Engine>,
        recorder: Option<Arc<Recorder>>,
        admission: Arc<Admission>,
        metrics: Arc<Metrics>,
    ) -> Self {
        Self {
            mesh: Arc::new(convert::mesh(engine.mesh())),
            engine,
            recorder,
            admission,
            metrics,
            started: Instant::now(),
            inline_while: tokio::runtime::Handle::try_current()
                .map_or(1, |runtime| runtime.metrics().num_workers().saturating_sub(1))
                .max(1),
        }
    }

    /// Answers one request, counts it, and hands the exchange to the recorder, if recording.
    async fn predict_one(
        &self,
        message: pb::PredictRequest,
        deadline: Option<Instant>,
        admitted: Option<Admitted>,
    ) -> Result<pb::PredictResponse, Status> {
        let received = SystemTime::now();
        let answer = self.answer(&message, deadline, admitted).await;
        match &answer {
            Ok(response) => self
                .metrics
                .observe(&response.model, Code::Ok, response.timing.as_ref()),
            Err(status) => {
                let model = self.engine.resolve_model_name(&message.model);
                self.metrics.observe(model, status.code(), None)
            }
        }
        if let Some(recorder) = &self.recorder {
            recorder.record(Exchange {
                received,
                answered: SystemTime::now(),
                response: answer.clone().map_err(|s| (s.code() as i32, s.message().to_owned())),
                request: message,
            });
        }
        answer
    }

    /// Answers one request: quick ones on this thread, the rest on the compute pool.
    ///
    /// A prior over the phantom takes about 50 µs on one core; handing it to the pool and back costs
    /// two thread wake-ups, each 15–40 µs on a small virtual machine, so requests the engine calls
    /// quick ([`Engine::is_quick`]) are computed here, blocking this runtime thread no longer than a
    /// wake-up or two would have, as long as the server is not busy: with as many requests holding
    /// places as the runtime has threads but one, a quick request goes to the pool too, so that a
    /// runtime thread stays free to read calls and refuse those beyond the bound. Networks and exact
    /// solves (milliseconds, parallel inside) always go to rayon's pool, leaving the runtime's threads
    /// to network I/O: run inline they would stall every other connection.
    ///
    /// Only admitted requests are computed (`admitted`: the place a unary call took at its arrival;
    /// a stream's message takes one here), and nothing is computed for a caller that has gone or
    /// whose deadline has passed.
    async fn answer(
        &self,
        message: &pb::PredictRequest,
        deadline: Option<Instant>,
        admitted: Option<Admitted>,
    ) -> Result<pb::PredictResponse, Status> {
        let received = Instant::now();
        let request = convert::request(message)?;
        let permit = match admitted {
            Some(place) => place,
            None => Admitted(Arc::new(
                self.admission.try_admit().ok_or_else(|| self.admission.at_capacity())?,
            )),
        };
        let refusal = |e: EngineError| {
            let status = convert::status(&e);
            if status.code() == Code::Internal {
                warn!(sequence = message.sequence, error = %e, "prediction failed");
            } else {
                debug!(sequence = message.sequence, error = %e, "request refused");
            }
            status
        };
        let prepared = self.engine.prepare(&request).map_err(refusal)?;
        // While others are being answered, a runtime thread that computed would leave calls unread
        // (and unrefused) behind it: then even a quick request goes to the pool, whose threads yield
        // to the runtime's (--compute-niceness).
        let inline = self.admission.in_flight() <= self.inline_while;
        let outcome = if inline && self.engine.is_quick(&prepared, &request) {
            let _permit = permit;
            if deadline.is_some_and(|d| received >= d) {
                self.admission.count_expired();
                return Err(Status::deadline_exceeded(
                    "the deadline had passed when the request arrived; nothing was computed",
                ));
            }
            self.engine.compute(prepared, &request)
        } else {
            self.on_pool(prepared, request, permit, deadline, &message.model)
                .await?
        };
        let mut prediction = outcome.map_err(refusal)?;
        // The server's whole time, hand-offs included, not only the engine's.
        prediction.timing.total_us = received.elapsed().as_secs_f32() * 1e6;
        Ok(convert::response(message.sequence, prediction))
    }

    /// Computes `prepared` on rayon's pool; the pool skips it if the caller has gone or its deadline
    /// passed while it waited.
    async fn on_pool(
        &self,
        prepared: Prepared,
        request: engine::Request,
        permit: Admitted,
        deadline: Option<Instant>,
        model: &str,
    ) -> Result<Result<Prediction, EngineError>, Status> {
        let engine = self.engine.clone();
        let admission = self.admission.clone();
        let waiting = Instant::now();
        let computing = Arc::new(AtomicBool::new(false));
        // None: the deadline passed before the pool reached the request.
        let (tx, rx) = tokio::sync::oneshot::channel();
        let started = computing.clone();
        rayon::spawn(move || {
            let _permit = permit;
            if tx.is_closed() {
                admission.count_abandoned();
            } else if deadline.is_some_and(|d| Instant::now() >= d) {
                admission.count_abandoned();
                let _ = tx.send(None);
            } else {
                started.store(true, Ordering::Release);
                let _ = tx.send(Some(engine.compute(prepared, &request)));
            }
        });
        let late = || {
            self.admission.count_expired();
            let elapsed_ms = waiting.elapsed().as_secs_f64() * 1e3;
            if computing.load(Ordering::Acquire) {
                // A model slower than its callers' deadlines (or hung): the answer is given on time,
                // the computation finishes in the pool and keeps its place until then.
                warn!(model, elapsed_ms, "deadline passed while computing");
                Status::deadline_exceeded(format!(
                    "the deadline passed after {elapsed_ms:.1} ms while the model was still computing"
                ))
            } else {
                Status::deadline_exceeded(format!(
                    "the deadline passed after {elapsed_ms:.1} ms waiting for the compute pool; nothing was computed"
                ))
            }
        };
        let outcome = match deadline {
            Some(d) => tokio::time::timeout_at(d.into(), rx).await.map_err(|_| late())?,
            None => rx.await,
        };
        outcome
            .map_err(|_| Status::internal("the prediction was abandoned (worker panicked)"))?
            .ok_or_else(late)
    }
}

type ResponseStream = Pin<Box<dyn Stream<Item = Result<pb::PredictResponse, Status>> + Send>>;

#[tonic::async_trait]
impl Deformation for DeformationService {
    async fn get_mesh(&self, request: Request<pb::GetMeshRequest>) -> Result<Response<pb::Mesh>, Status> {
        let wanted = &request.get_ref().mesh;
        if !self.engine.serves_mesh(wanted) {
            return Err(Status::not_found(format!(
                "mesh {wanted:?} is not served here; this server serves {:?}",
                self.engine.mesh().config.name
            )));
        }
        Ok(Response::new(self.mesh.as_ref().clone()))
    }

    async fn get_status(&self, _request: Request<pb::GetStatusRequest>) -> Result<Response<pb::ServerStatus>, Status> {
        Ok(Response::new(pb::ServerStatus {
            version: env!("CARGO_PKG_VERSION").to_owned(),
            uptime_ms: self.started.elapsed().as_millis() as u64,
            recorder: Some(self.recorder.as_ref().map_or_else(Default::default, |r| r.status())),
            admission: Some(self.admission.status()),
            refused_models: self
                .engine
                .refused_models()
                .iter()
                .map(|r| pb::RefusedModel {
                    origin: r.origin.clone(),
                    reason: r.reason.clone(),
                })
                .collect(),
        }))
    }

    async fn list_models(
        &self,
        _request: Request<pb::ListModelsRequest>,
    ) -> Result<Response<pb::ListModelsResponse>, Status> {
        let models = self.engine.models().map(convert::model_info).collect();
        Ok(Response::new(pb::ListModelsResponse {
            models,
            default_model: self.engine.default_model().to_owned(),
        }))
    }

    async fn predict(&self, mut request: Request<pb::PredictRequest>) -> Result<Response<pb::PredictResponse>, Status> {
        let deadline = admission::deadline(request.metadata(), arrival::arrival(&request));
        let admitted = arrival::admitted(&mut request);
        self.predict_one(request.into_inner(), deadline, admitted)
            .await
            .map(Response::new)
    }

    type PredictStreamStream = ResponseStream;

    async fn predict_stream(
        &self,
        request: Request<Streaming<pb::PredictRequest>>,
    ) -> Result<Response<Self::PredictStreamStream>, Status> {
        // A stream's deadline is its call's: every message must be answered before it.
        let deadline = admission::deadline(request.metadata(), arrival::arrival(&request));
        let mut incoming = request.into_inner();
        let service = self.clone();
        // Requests are answered one at a time as they arrive, so answers keep their order. A refused
        // request is answered with `error` set; only a broken stream ends the call.
        let outgoing = async_stream(move |tx| async move {
            while let Some(next) = incoming.next().await {
                let answer = match next {
                    Ok(message) => {
                        let sequence = message.sequence;
                        Ok(service
                            .predict_one(message, deadline, None)
                            .await
                            .unwrap_or_else(|status| pb::PredictResponse {
                                sequence,
                                error: Some(pb::StreamError {
                                    code: status.code() as i32,
                                    message: status.message().to_owned(),
                                }),
                                ..Default::default()
                            }))
                    }
                    Err(status) if status.message().contains(TOO_LARGE) => {
                        Err(Status::resource_exhausted(status.message().to_owned()))
                    }
                    Err(status) => Err(status),
                };
                let stop = answer.is_err();
                if tx.send(answer).await.is_err() || stop {
                    break;
                }
            }
        });
        Ok(Response::new(Box::pin(outgoing)))
    }
}

/// A response stream fed by a task: the task ends when the client cancels (the receiver is dropped).
fn async_stream<F, Fut>(body: F) -> impl Stream<Item = Result<pb::PredictResponse, Status>>
where
    F: FnOnce(tokio::sync::mpsc::Sender<Result<pb::PredictResponse, Status>>) -> Fut,
    Fut: std::future::Future<Output = ()> + Send + 'static,
{
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    tokio::spawn(body(tx));
    tokio_stream::wrappers::ReceiverStream::new(rx)
}
