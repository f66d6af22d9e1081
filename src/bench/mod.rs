//! `nak bench`: a latency load tester for nak servers.
//!
//! Closed loop (`rate = None`): each of `concurrency` workers sends its next request as soon as the
//! last one is answered. Open loop (`rate = Some(r)`): requests are due at a constant rate and sent
//! when due whether or not earlier ones were answered (unary calls each on their own HTTP/2 stream),
//! and latency is measured from when a request was *due*, not when it went out, so a server that
//! falls behind shows its queueing instead of hiding it (coordinated omission). Answers and refusals
//! are timed apart: under overload, how fast a refusal comes matters as much as an answer. Requests are drawn from the paper's
//! distribution p over the mesh the server reports, reproducibly from the seed.

mod host;
mod pacer;
mod report;
mod requests;

use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use hdrhistogram::Histogram;
use tokio::time::Instant;

use host::Usage;
pub use report::{GpuSummary, Interval, Percentiles, Report};
pub use requests::{RequestsError, draw, sampler_for};

use crate::client::{Client, ClientConfig, ClientError, connect};
use crate::proto::v1::PredictRequest;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    Unary,
    Stream,
}

#[derive(Debug, Clone, PartialEq)]
pub struct BenchConfig {
    /// The servers and how to reach them (several: requests are spread over them).
    pub connection: ClientConfig,
    pub model: String,
    pub mode: Mode,
    /// Workers (unary) or streams (stream mode), each on its own connection.
    pub concurrency: usize,
    /// Offered load in requests per second over all workers; `None`: closed loop, as fast as answered.
    pub rate: Option<f64>,
    pub duration: Duration,
    /// Sent but not measured, before the measured window.
    pub warmup: Duration,
    pub graspers: usize,
    pub seed: u64,
    /// Distinct requests drawn (cycled through).
    pub distinct_requests: usize,
    /// Percentiles also per interval of this length (latency over time, for soak tests).
    pub interval: Option<Duration>,
}

#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error(transparent)]
    Connect(#[from] ClientError),
    #[error(transparent)]
    Requests(#[from] RequestsError),
    #[error("invalid configuration: {0}")]
    Config(String),
    #[error("cannot make the open-loop timer: {0}")]
    Timer(#[from] std::io::Error),
}

/// A live view of a running test, for progress displays.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Progress {
    pub elapsed: Duration,
    pub total: Duration,
    pub completed: u64,
    pub errors: u64,
    pub p50_us: f64,
    pub p99_us: f64,
}

/// Latencies and outcomes of the measured window, shared by the workers.
struct Tally {
    window: (Instant, Instant),
    latency: Mutex<Histogram<u64>>,
    answered: Mutex<Histogram<u64>>,
    refused: Mutex<Histogram<u64>>,
    server: Mutex<Histogram<u64>>,
    queue: Mutex<Histogram<u64>>,
    prior: Mutex<Histogram<u64>>,
    gpu: GpuTally,
    generator: Mutex<Histogram<u64>>,
    errors: Mutex<BTreeMap<String, u64>>,
    /// The first message seen with each error code.
    error_examples: Mutex<BTreeMap<String, String>>,
    intervals: Option<Intervals>,
    completed: AtomicU64,
    failed: AtomicU64,
}

/// Outcomes per interval of the measured window (`--interval`).
struct Intervals {
    length: Duration,
    slots: Mutex<Vec<Slot>>,
}

/// One interval's latencies, every outcome, and how many were refusals.
struct Slot {
    latency: Histogram<u64>,
    refused: u64,
}

/// 1 µs to 100 s at 3 significant digits.
fn histogram() -> Result<Histogram<u64>, BenchError> {
    Histogram::new_with_bounds(1, 100_000_000, 3).map_err(|e| BenchError::Config(format!("histogram: {e}")))
}

impl Tally {
    fn new(window: (Instant, Instant), interval: Option<Duration>) -> Result<Self, BenchError> {
        let intervals = match interval {
            Some(length) if length.is_zero() => return Err(BenchError::Config("the interval must be positive".into())),
            Some(length) => {
                let count = (window.1 - window.0).as_secs_f64() / length.as_secs_f64();
                let slots = (0..count.ceil() as usize)
                    .map(|_| histogram().map(|latency| Slot { latency, refused: 0 }))
                    .collect::<Result<_, _>>()?;
                Some(Intervals {
                    length,
                    slots: Mutex::new(slots),
                })
            }
            None => None,
        };
        Ok(Self {
            window,
            latency: Mutex::new(histogram()?),
            answered: Mutex::new(histogram()?),
            refused: Mutex::new(histogram()?),
            server: Mutex::new(histogram()?),
            queue: Mutex::new(histogram()?),
            prior: Mutex::new(histogram()?),
            gpu: GpuTally {
                answers: AtomicU64::new(0),
                dispatched: AtomicU64::new(0),
                queue: Mutex::new(histogram()?),
                submit: Mutex::new(histogram()?),
                wait: Mutex::new(histogram()?),
                copy: Mutex::new(histogram()?),
            },
            generator: Mutex::new(histogram()?),
            errors: Mutex::new(BTreeMap::new()),
            error_examples: Mutex::new(BTreeMap::new()),
            intervals,
            completed: AtomicU64::new(0),
            failed: AtomicU64::new(0),
        })
    }

    fn snapshot(shared: &Mutex<Histogram<u64>>) -> Result<Histogram<u64>, BenchError> {
        match shared.lock() {
            Ok(h) => Ok(h.clone()),
            Err(_) => histogram(),
        }
    }

    fn in_window(&self, due: Instant) -> bool {
        due >= self.window.0 && due < self.window.1
    }

    /// Records how long after its due time a request was handed to the gRPC client.
    fn record_sent(&self, due: Instant, sent: Instant) {
        if self.in_window(due) {
            record(&self.generator, (sent - due).as_micros().max(1) as u64);
        }
    }

    /// Records one answer to a request due at `due`; answers to requests due outside the window are
    /// not counted.
    fn record(&self, due: Instant, outcome: Result<ServerTime, Refusal>) {
        if !self.in_window(due) {
            return;
        }
        let micros = due.elapsed().as_micros().max(1) as u64;
        record(&self.latency, micros);
        self.completed.fetch_add(1, Ordering::Relaxed);
        if let Some(intervals) = &self.intervals {
            let index = ((due - self.window.0).as_secs_f64() / intervals.length.as_secs_f64()) as usize;
            if let Ok(mut slots) = intervals.slots.lock()
                && let Some(slot) = slots.get_mut(index)
            {
                slot.latency.saturating_record(micros);
                slot.refused += u64::from(outcome.is_err());
            }
        }
        match outcome {
            Ok(server) => {
                record(&self.answered, micros);
                record(&self.server, server.total_us.max(1.0) as u64);
                record(&self.queue, server.queue_us.max(1.0) as u64);
                record(&self.prior, server.prior_us.max(1.0) as u64);
                if let Some(gpu) = server.gpu {
                    self.gpu.record(gpu);
                }
            }
            Err(Refusal { code, message }) => {
                record(&self.refused, micros);
                self.failed.fetch_add(1, Ordering::Relaxed);
                if let Ok(mut examples) = self.error_examples.lock() {
                    examples.entry(code.clone()).or_insert(message);
                }
                if let Ok(mut errors) = self.errors.lock() {
                    *errors.entry(code).or_default() += 1;
                }
            }
        }
    }

    /// Percentiles per interval, in order.
    fn intervals(&self) -> Vec<Interval> {
        let Some(intervals) = &self.intervals else {
            return Vec::new();
        };
        let Ok(slots) = intervals.slots.lock() else {
            return Vec::new();
        };
        slots
            .iter()
            .enumerate()
            .map(|(i, slot)| Interval {
                start_s: i as f64 * intervals.length.as_secs_f64(),
                requests: slot.latency.len(),
                refused: slot.refused,
                latency_us: Percentiles::of(&slot.latency),
            })
            .collect()
    }

    fn progress(&self, start: Instant, total: Duration) -> Progress {
        let (p50_us, p99_us) = self
            .latency
            .lock()
            .map(|h| (h.value_at_quantile(0.5) as f64, h.value_at_quantile(0.99) as f64))
            .unwrap_or_default();
        Progress {
            elapsed: start.elapsed(),
            total,
            completed: self.completed.load(Ordering::Relaxed),
            errors: self.failed.load(Ordering::Relaxed),
            p50_us,
            p99_us,
        }
    }
}

fn record(h: &Mutex<Histogram<u64>>, value: u64) {
    if let Ok(mut h) = h.lock() {
        h.saturating_record(value);
    }
}

/// The GPU phases of the answers whose prior ran there (`Timing.gpu`).
struct GpuTally {
    answers: AtomicU64,
    /// Requests served by the dispatches of those answers, summed per answer.
    dispatched: AtomicU64,
    queue: Mutex<Histogram<u64>>,
    /// Upload and dispatch.
    submit: Mutex<Histogram<u64>>,
    wait: Mutex<Histogram<u64>>,
    copy: Mutex<Histogram<u64>>,
}

impl GpuTally {
    fn record(&self, t: crate::proto::v1::GpuTiming) {
        self.answers.fetch_add(1, Ordering::Relaxed);
        self.dispatched.fetch_add(u64::from(t.batch), Ordering::Relaxed);
        let micros = |v: f32| v.max(1.0) as u64;
        record(&self.queue, micros(t.queue_us));
        record(&self.submit, micros(t.upload_us + t.dispatch_us));
        record(&self.wait, micros(t.wait_us));
        record(&self.copy, micros(t.copy_us));
    }

    fn summary(&self) -> Result<Option<GpuSummary>, BenchError> {
        let answers = self.answers.load(Ordering::Relaxed);
        if answers == 0 {
            return Ok(None);
        }
        let of = |h: &Mutex<Histogram<u64>>| Tally::snapshot(h).map(|h| Percentiles::of(&h));
        Ok(Some(GpuSummary {
            requests_per_dispatch: self.dispatched.load(Ordering::Relaxed) as f64 / answers as f64,
            queue_us: of(&self.queue)?,
            submit_us: of(&self.submit)?,
            wait_us: of(&self.wait)?,
            copy_us: of(&self.copy)?,
        }))
    }
}

/// The server's account of one answer (`Timing`).
#[derive(Debug, Clone, Copy, Default)]
struct ServerTime {
    total_us: f32,
    queue_us: f32,
    prior_us: f32,
    /// Where the prior's time went, when it ran on the GPU.
    gpu: Option<crate::proto::v1::GpuTiming>,
}

impl ServerTime {
    fn of(timing: Option<crate::proto::v1::Timing>) -> Self {
        timing.map_or_else(Self::default, |t| Self {
            total_us: t.total_us,
            queue_us: t.queue_us,
            prior_us: t.prior_us,
            gpu: t.gpu,
        })
    }
}

/// An answer that was not a prediction: its gRPC status code's name and its message.
#[derive(Debug, Clone)]
struct Refusal {
    code: String,
    message: String,
}

impl Refusal {
    fn of(status: &tonic::Status) -> Self {
        Self {
            code: code_name(status.code()),
            message: status.message().to_owned(),
        }
    }
}

/// `INVALID_ARGUMENT` for `Code::InvalidArgument`: the names gRPC documentation uses.
fn code_name(code: tonic::Code) -> String {
    let camel = format!("{code:?}");
    let mut name = String::new();
    for (i, c) in camel.chars().enumerate() {
        if c.is_uppercase() && i > 0 {
            name.push('_');
        }
        name.push(c.to_ascii_uppercase());
    }
    name
}

/// Runs one load test; `progress` is called about four times a second.
pub async fn run(config: &BenchConfig, progress: impl Fn(Progress)) -> Result<Report, BenchError> {
    if config.concurrency == 0 || config.rate.is_some_and(|r| r.is_nan() || r <= 0.0) || config.distinct_requests == 0 {
        return Err(BenchError::Config(
            "concurrency, rate and distinct requests must be positive".into(),
        ));
    }
    let mut first = connect(&config.connection).await?;
    let sampler = sampler_for(&mut first).await?;
    let pool = Arc::new(draw(
        &sampler,
        &config.model,
        config.graspers,
        config.seed,
        config.distinct_requests,
    )?);
    let mut clients = vec![first];
    for _ in 1..config.concurrency {
        clients.push(connect(&config.connection).await?);
    }

    let start = Instant::now() + Duration::from_millis(50);
    let measure_from = start + config.warmup;
    let end = measure_from + config.duration;
    let tally = Arc::new(Tally::new((measure_from, end), config.interval)?);
    let counter = Arc::new(AtomicU64::new(0));
    let mut pacer_queues = Vec::new();
    let mut workers = tokio::task::JoinSet::new();
    for client in clients {
        let due = config.rate.map(|_| {
            let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
            pacer_queues.push(tx);
            rx
        });
        let job = Job {
            client,
            pool: pool.clone(),
            tally: tally.clone(),
            counter: counter.clone(),
            due,
            start,
            end,
        };
        match config.mode {
            Mode::Unary => workers.spawn(job.unary()),
            Mode::Stream => workers.spawn(job.stream()),
        };
    }
    if let Some(rate) = config.rate {
        tokio::spawn(pace(pacer::Pacer::new()?, rate, start, end, pacer_queues));
    }
    // Read when measuring starts, not now: the warm-up is not part of the report.
    let usage_from = tokio::spawn(async move {
        tokio::time::sleep_until(measure_from).await;
        Usage::now()
    });
    let total = end - start;
    let mut ticker = tokio::time::interval(Duration::from_millis(250));
    loop {
        tokio::select! {
            done = workers.join_next() => if done.is_none() { break },
            _ = ticker.tick() => progress(tally.progress(start, total)),
        }
    }
    progress(tally.progress(start, total));

    let latency = Tally::snapshot(&tally.latency)?;
    let answered = Tally::snapshot(&tally.answered)?;
    let refused = Tally::snapshot(&tally.refused)?;
    let server = Tally::snapshot(&tally.server)?;
    let queue = Tally::snapshot(&tally.queue)?;
    let prior = Tally::snapshot(&tally.prior)?;

    let generator = Tally::snapshot(&tally.generator)?;
    let requests = latency.len();
    let usage_to = Usage::now();
    // A run that ended before measuring started has no window to report on.
    let usage_from = if usage_from.is_finished() {
        usage_from.await.ok()
    } else {
        usage_from.abort();
        None
    };
    let steal_percent = usage_from.and_then(|from| from.steal_percent_until(&usage_to));
    let client_cpu_us = usage_from
        .and_then(|from| from.process_time_until(&usage_to))
        .filter(|_| requests > 0)
        .map(|spent| spent.as_secs_f64() * 1e6 / requests as f64);
    Ok(Report {
        target: config.connection.targets.clone(),
        model: config.model.clone(),
        mode: match config.mode {
            Mode::Unary => "unary".into(),
            Mode::Stream => "stream".into(),
        },
        concurrency: config.concurrency,
        rate_rps: config.rate,
        duration_s: config.duration.as_secs_f64(),
        graspers: config.graspers,
        seed: config.seed,
        requests,
        throughput_rps: requests as f64 / config.duration.as_secs_f64(),
        latency_us: Percentiles::of(&latency),
        answered_us: Percentiles::of(&answered),
        refused_us: (!refused.is_empty()).then(|| Percentiles::of(&refused)),
        server_us: Percentiles::of(&server),
        server_queue_us: Percentiles::of(&queue),
        server_prior_us: Percentiles::of(&prior),
        gpu: tally.gpu.summary()?,
        generator_us: Percentiles::of(&generator),
        errors: tally.errors.lock().map(|e| e.clone()).unwrap_or_default(),
        error_examples: tally.error_examples.lock().map(|e| e.clone()).unwrap_or_default(),
        intervals: tally.intervals(),
        steal_percent,
        client_cpu_us,
    })
}

/// One worker's share of the test. Open loop: `due` yields (request number, due time) from the pacer;
/// closed loop: `due` is `None` and the worker sends as soon as its last answer arrived.
struct Job {
    client: Client,
    pool: Arc<Vec<PredictRequest>>,
    tally: Arc<Tally>,
    counter: Arc<AtomicU64>,
    due: Option<tokio::sync::mpsc::UnboundedReceiver<(u64, Instant)>>,
    start: Instant,
    end: Instant,
}

fn request(pool: &[PredictRequest], k: u64) -> PredictRequest {
    let mut r = pool[(k % pool.len() as u64) as usize].clone();
    r.sequence = k;
    r
}

/// Releases request k at `start + k / rate` to worker `k mod workers`.
///
/// The generator's thread sleeps until shortly before each due time and spins the rest: waking an
/// idle virtual CPU takes tens of µs, which would count as the server's latency. The spin is at
/// most 100 µs and a tenth of the interval between requests, so at most a tenth of a core.
async fn pace(
    mut pacer: pacer::Pacer,
    rate: f64,
    start: Instant,
    end: Instant,
    workers: Vec<tokio::sync::mpsc::UnboundedSender<(u64, Instant)>>,
) {
    let early = Duration::from_secs_f64((0.1 / rate).min(100e-6));
    for k in 0u64.. {
        let due = start + Duration::from_secs_f64(k as f64 / rate);
        if due >= end {
            break;
        }
        if let Err(e) = pacer.until(due, early).await {
            tracing::error!("the open-loop timer failed, no more requests are sent: {e}");
            break;
        }
        // A worker that has gone (its connection failed) simply receives no more.
        let _ = workers[(k % workers.len() as u64) as usize].send((k, due));
    }
}

impl Job {
    /// Next request number and its due time; `None` when the test is over.
    async fn next(&mut self) -> Option<(u64, Instant)> {
        match &mut self.due {
            Some(due) => due.recv().await,
            None => {
                let now = Instant::now();
                if now < self.start {
                    tokio::time::sleep_until(self.start).await;
                }
                let now = Instant::now();
                (now < self.end).then(|| (self.counter.fetch_add(1, Ordering::Relaxed), now))
            }
        }
    }

    /// Closed loop: one call at a time. Open loop: each call when due, on its own HTTP/2 stream of
    /// the worker's connection, however many are still unanswered.
    async fn unary(mut self) {
        let open_loop = self.due.is_some();
        let mut unanswered = tokio::task::JoinSet::new();
        while let Some((k, due)) = self.next().await {
            let call = Self::call(self.client.clone(), request(&self.pool, k), due, self.tally.clone());
            if open_loop {
                unanswered.spawn(call);
                while unanswered.try_join_next().is_some() {}
            } else {
                call.await;
            }
        }
        while unanswered.join_next().await.is_some() {}
    }

    async fn call(mut client: Client, request: PredictRequest, due: Instant, tally: Arc<Tally>) {
        tally.record_sent(due, Instant::now());
        let outcome = match client.predict(request).await {
            Ok(r) => Ok(ServerTime::of(r.into_inner().timing)),
            Err(status) => Err(Refusal::of(&status)),
        };
        tally.record(due, outcome);
    }

    /// One stream: a sender task sends requests when due (open loop) or when the previous answer
    /// arrived (closed loop), and this task matches answers, which come in order, to their due times.
    async fn stream(mut self) {
        let (tx, rx) = tokio::sync::mpsc::channel::<PredictRequest>(64);
        let mut answers = match self
            .client
            .predict_stream(tokio_stream::wrappers::ReceiverStream::new(rx))
            .await
        {
            Ok(r) => r.into_inner(),
            Err(status) => {
                self.tally.record(self.tally.window.0, Err(Refusal::of(&status)));
                return;
            }
        };
        let due_times: Arc<Mutex<VecDeque<Instant>>> = Arc::default();
        let (answered_tx, mut answered_rx) = tokio::sync::mpsc::channel::<()>(1);
        let closed_loop = self.due.is_none();
        let pool = self.pool.clone();
        let tally = self.tally.clone();
        let sender = {
            let due_times = due_times.clone();
            let tally_sent = tally.clone();
            tokio::spawn(async move {
                let mut first = true;
                loop {
                    if closed_loop && !first && answered_rx.recv().await.is_none() {
                        break;
                    }
                    first = false;
                    let Some((k, due)) = self.next().await else {
                        break;
                    };
                    if let Ok(mut d) = due_times.lock() {
                        d.push_back(due);
                    }
                    tally_sent.record_sent(due, Instant::now());
                    if tx.send(request(&pool, k)).await.is_err() {
                        break;
                    }
                }
            })
        };
        loop {
            let answer = answers.message().await;
            let Some(due) = due_times.lock().ok().and_then(|mut d| d.pop_front()) else {
                break;
            };
            let (outcome, last) = match answer {
                Ok(Some(r)) => match r.error {
                    Some(e) => {
                        let code = code_name(tonic::Code::from_i32(e.code));
                        (
                            Err(Refusal {
                                code,
                                message: e.message,
                            }),
                            false,
                        )
                    }
                    None => (Ok(ServerTime::of(r.timing)), false),
                },
                Ok(None) => break,
                Err(status) => (Err(Refusal::of(&status)), true),
            };
            tally.record(due, outcome);
            if last || (closed_loop && answered_tx.send(()).await.is_err()) {
                break;
            }
        }
        sender.abort();
    }
}
