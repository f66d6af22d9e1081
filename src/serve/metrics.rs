//! Prometheus metrics (`nak serve --metrics-listen ADDR`), served as OpenMetrics text at `/metrics` on
//! a port of their own, so that scraping never shares a connection (or a TLS and token setup) with
//! gRPC callers.
//!
//! Request counts and latency histograms are updated per answer; admission, recorder and model
//! figures are read from their owners at scrape time rather than kept twice.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeLabelSet, EncodeMetric};
use prometheus_client::metrics::counter::{ConstCounter, Counter};
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::{Registry, Unit};
use tokio::net::TcpListener;
use tonic::Code;

use super::admission::Admission;
use crate::engine::{Engine, ModelKind};
use crate::proto::v1::Timing;
use crate::record::Recorder;

/// Label for requests naming a model this server does not serve: callers choose the name, and one
/// series per typo would grow without bound.
const UNKNOWN_MODEL: &str = "unknown";

#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RequestLabels {
    model: Arc<String>,
    /// The gRPC status code's name, as grpc-go's interceptors write it (`Ok`, `InvalidArgument`).
    code: Arc<String>,
}

#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
struct ModelLabels {
    model: Arc<String>,
}

#[derive(Debug, Clone, Hash, PartialEq, Eq, EncodeLabelSet)]
struct ModelInfoLabels {
    model: String,
    kind: String,
    regime: String,
}

type Latency = Family<ModelLabels, Histogram, fn() -> Histogram>;

/// Histogram buckets from 25 µs to ~1.6 s, doubling: the prior alone takes tens of µs, a network a
/// few ms, an exact solve on a large mesh up to a second.
fn latency_histogram() -> Histogram {
    Histogram::new(exponential_buckets(25e-6, 2.0, 17))
}

/// One model's label and latency histograms, looked up once at start: answering a request then costs
/// no allocation and no lock beyond the request counter's.
#[derive(Debug)]
struct ModelSeries {
    label: Arc<String>,
    server: Histogram,
    prior: Histogram,
    /// For models with a network stage.
    network: Option<Histogram>,
}

/// What one server reports to Prometheus.
#[derive(Debug)]
pub struct Metrics {
    registry: Registry,
    requests: Family<RequestLabels, Counter>,
    models: HashMap<String, ModelSeries>,
    /// Requests naming a model this server does not serve (never answered, so never timed).
    unknown: Arc<String>,
    /// Each gRPC code's name, by its number.
    codes: Vec<Arc<String>>,
}

impl Metrics {
    pub fn new(engine: Arc<Engine>, admission: Arc<Admission>, recorder: Option<Arc<Recorder>>) -> Self {
        let requests = Family::<RequestLabels, Counter>::default();
        let [server, prior, network]: [Latency; 3] =
            std::array::from_fn(|_| Family::new_with_constructor(latency_histogram as fn() -> Histogram));
        let models = engine
            .models()
            .map(|m| {
                let labels = ModelLabels {
                    model: Arc::new(m.name.clone()),
                };
                let series = ModelSeries {
                    server: server.get_or_create_owned(&labels),
                    prior: prior.get_or_create_owned(&labels),
                    network: (m.kind == ModelKind::Neural).then(|| network.get_or_create_owned(&labels)),
                    label: labels.model,
                };
                (m.name.clone(), series)
            })
            .collect();
        let mut registry = Registry::with_prefix("nak");
        registry.register(
            "requests",
            "Predict calls and stream messages answered, by model and gRPC status code",
            requests.clone(),
        );
        let latencies = [
            (
                "server_latency",
                "Server time per answered request, from decoded request to response ready (Timing.total_us)",
                server,
            ),
            (
                "prior_latency",
                "Time evaluating the prior per answered request (Timing.prior_us)",
                prior,
            ),
            (
                "network_latency",
                "Time evaluating the network per answered request, for models with one (Timing.network_us)",
                network,
            ),
        ];
        for (name, help, family) in latencies {
            registry.register_with_unit(name, help, Unit::Seconds, family);
        }
        registry.register_collector(Box::new(State {
            engine,
            admission,
            recorder,
            started: Instant::now(),
        }));
        Self {
            registry,
            requests,
            models,
            unknown: Arc::new(UNKNOWN_MODEL.to_owned()),
            codes: (0..=Code::Unauthenticated as i32)
                .map(|c| Arc::new(format!("{:?}", Code::from_i32(c))))
                .collect(),
        }
    }

    /// Counts one answer (or refusal) by `model` (the one that answered: a request naming none is
    /// counted under the engine's default), with its stage times when answered.
    pub fn observe(&self, model: &str, code: Code, timing: Option<&Timing>) {
        let series = self.models.get(model);
        let labels = RequestLabels {
            model: series.map_or(&self.unknown, |s| &s.label).clone(),
            code: self.codes[code as usize].clone(),
        };
        self.requests.get_or_create(&labels).inc();
        let (Some(series), Some(timing)) = (series, timing) else {
            return;
        };
        series.server.observe(f64::from(timing.total_us) * 1e-6);
        series.prior.observe(f64::from(timing.prior_us) * 1e-6);
        if let Some(network) = &series.network {
            network.observe(f64::from(timing.network_us) * 1e-6);
        }
    }

    /// Counts a unary call refused at its arrival, before its request (and so its model) was read.
    pub fn observe_refused_at_arrival(&self) {
        let labels = RequestLabels {
            model: self.unknown.clone(),
            code: self.codes[Code::ResourceExhausted as usize].clone(),
        };
        self.requests.get_or_create(&labels).inc();
    }

    /// The OpenMetrics text exposition of every metric.
    pub fn encode(&self) -> String {
        let mut text = String::new();
        // Writing to a String cannot fail.
        let _ = prometheus_client::encoding::text::encode(&mut text, &self.registry);
        text
    }
}

/// Figures owned elsewhere, read at each scrape.
struct State {
    engine: Arc<Engine>,
    admission: Arc<Admission>,
    recorder: Option<Arc<Recorder>>,
    started: Instant,
}

impl std::fmt::Debug for State {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("State").finish_non_exhaustive()
    }
}

impl Collector for State {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        let admission = self.admission.status();
        let gauge = |value: u64| ConstGauge::new(value as i64);
        let counter = ConstCounter::new;
        emit(
            &mut encoder,
            "in_flight",
            "Requests admitted and not yet answered (computing or waiting for the compute pool).",
            gauge(admission.in_flight),
        )?;
        emit(
            &mut encoder,
            "max_in_flight",
            "The admission bound (--max-in-flight).",
            gauge(admission.max_in_flight),
        )?;
        emit(
            &mut encoder,
            "admission_refused",
            "Requests refused RESOURCE_EXHAUSTED because max_in_flight requests were admitted.",
            counter(admission.refused),
        )?;
        emit(
            &mut encoder,
            "deadline_expired",
            "Requests answered DEADLINE_EXCEEDED.",
            counter(admission.expired),
        )?;
        emit(
            &mut encoder,
            "abandoned",
            "Admitted requests not computed because their caller had gone or their deadline had passed.",
            counter(admission.abandoned),
        )?;
        emit(
            &mut encoder,
            "models_loaded",
            "Models served.",
            gauge(self.engine.models().count() as u64),
        )?;
        let mut served = encoder.encode_descriptor(
            "model",
            "One series per model served, with its kind and regime (value 1).",
            None,
            prometheus_client::metrics::MetricType::Gauge,
        )?;
        for model in self.engine.models() {
            let labels = ModelInfoLabels {
                model: model.name.clone(),
                kind: format!("{:?}", model.kind).to_lowercase(),
                regime: model.regime.clone(),
            };
            ConstGauge::new(1).encode(served.encode_family(&labels)?)?;
        }
        emit(
            &mut encoder,
            "models_refused",
            "Models asked for at start but not loaded (GetStatus says why).",
            gauge(self.engine.refused_models().len() as u64),
        )?;
        let status = self.recorder.as_ref().map(|r| (r.status(), r.queued(), r.capacity()));
        let (recorded, dropped, queued, capacity) = status.map_or((0, 0, 0, 0), |(s, queued, capacity)| {
            (s.recorded, s.dropped, queued, capacity as u64)
        });
        emit(
            &mut encoder,
            "recorder_queue",
            "Exchanges waiting for the MCAP writer.",
            gauge(queued),
        )?;
        emit(
            &mut encoder,
            "recorder_queue_capacity",
            "The recorder queue's size (--record-queue; 0 when not recording).",
            gauge(capacity),
        )?;
        emit(
            &mut encoder,
            "recorder_recorded",
            "Exchanges written to MCAP.",
            counter(recorded),
        )?;
        emit(
            &mut encoder,
            "recorder_dropped",
            "Exchanges not recorded because the recorder's queue was full or its writer had stopped.",
            counter(dropped),
        )?;
        emit(
            &mut encoder,
            "uptime_seconds",
            "Seconds since the server started.",
            gauge(self.started.elapsed().as_secs()),
        )
    }
}

fn emit(encoder: &mut DescriptorEncoder, name: &str, help: &str, metric: impl EncodeMetric) -> std::fmt::Result {
    metric.encode(encoder.encode_descriptor(name, help, None, metric.metric_type())?)
}

/// Serves `GET /metrics` on `listener` until `shutdown` completes.
pub async fn serve(
    metrics: Arc<Metrics>,
    listener: TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    use axum::http::header::CONTENT_TYPE;
    let scrape = move || {
        let metrics = metrics.clone();
        async move {
            (
                [(
                    CONTENT_TYPE,
                    "application/openmetrics-text; version=1.0.0; charset=utf-8",
                )],
                metrics.encode(),
            )
        }
    };
    let app = axum::Router::new().route("/metrics", axum::routing::get(scrape));
    axum::serve(listener, app).with_graceful_shutdown(shutdown).await
}
