//! What a load test found: latency percentiles, throughput and errors, as a table and as JSON.

use std::collections::BTreeMap;

use hdrhistogram::Histogram;
use serde::Serialize;

/// Latency percentiles in microseconds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Percentiles {
    pub p50: f64,
    pub p90: f64,
    pub p99: f64,
    pub p999: f64,
    pub max: f64,
    pub mean: f64,
}

impl Percentiles {
    pub fn of(h: &Histogram<u64>) -> Self {
        let q = |q: f64| h.value_at_quantile(q) as f64;
        Self {
            p50: q(0.5),
            p90: q(0.9),
            p99: q(0.99),
            p999: q(0.999),
            max: h.max() as f64,
            mean: h.mean(),
        }
    }
}

/// One interval of the measured window (`nak bench --interval`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Interval {
    /// From the start of the measured window.
    pub start_s: f64,
    /// Requests due in it and answered or refused.
    pub requests: u64,
    pub refused: u64,
    pub latency_us: Percentiles,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    pub target: String,
    pub model: String,
    pub mode: String,
    pub concurrency: usize,
    /// Offered load; `None` for a closed loop at maximum rate.
    pub rate_rps: Option<f64>,
    pub duration_s: f64,
    pub graspers: usize,
    pub seed: u64,
    /// Answers received in the measured window (errors included).
    pub requests: u64,
    pub throughput_rps: f64,
    /// From the intended send time (open loop) or the actual one (closed loop) to the answer or
    /// refusal, over every outcome.
    pub latency_us: Percentiles,
    /// The same, for the successful answers only.
    pub answered_us: Percentiles,
    /// The same, for the refusals and errors only; `None` when there were none.
    pub refused_us: Option<Percentiles>,
    /// The server's own `Timing.total_us`, for the successful answers.
    pub server_us: Percentiles,
    /// The part of it spent waiting for a compute thread (`Timing.queue_us`).
    pub server_queue_us: Percentiles,
    /// The part of it spent evaluating the prior (`Timing.prior_us`).
    pub server_prior_us: Percentiles,
    /// Where the prior's time went for the answers whose prior ran on the GPU (`Timing.gpu`);
    /// `None` when none ran there.
    pub gpu: Option<GpuSummary>,
    /// How long after its due time each request was handed to the gRPC client: the load
    /// generator's own delay, which `latency_us` includes.
    pub generator_us: Percentiles,
    /// By gRPC status code name.
    pub errors: BTreeMap<String, u64>,
    /// The first message seen with each code in `errors`: where it came from (the server's words, or
    /// the client's when the call never got an answer).
    pub error_examples: BTreeMap<String, String>,
    /// Per `--interval`, in order; empty without it.
    pub intervals: Vec<Interval>,
    /// The share of this machine's CPU time that its hypervisor gave to other guests while measuring
    /// (`/proc/stat`); `None` where that is not known.
    pub steal_percent: Option<f64>,
    /// This process's CPU time (all threads, user and system) per request while measuring: what the
    /// load generator and its gRPC client cost; `None` where that is not known.
    pub client_cpu_us: Option<f64>,
}

/// The GPU phases of the prior over the answers evaluated there (server side, `Timing.gpu`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GpuSummary {
    /// Requests that shared an answer's dispatch, on average over the answers.
    pub requests_per_dispatch: f64,
    /// Waiting for a dispatch to take the request.
    pub queue_us: Percentiles,
    /// Writing the dispatch's inputs and submitting it.
    pub submit_us: Percentiles,
    /// From submission until the field was in mapped host memory.
    pub wait_us: Percentiles,
    /// Copying the field into the answer.
    pub copy_us: Percentiles,
}

impl Report {
    pub fn table(&self) -> String {
        let l = &self.latency_us;
        let s = &self.server_us;
        let rate = self
            .rate_rps
            .map_or("max (closed loop)".to_owned(), |r| format!("{r:.0}/s (open loop)"));
        let errors = if self.errors.is_empty() {
            "none".to_owned()
        } else {
            self.errors
                .iter()
                .map(|(k, v)| match self.error_examples.get(k) {
                    Some(example) => format!("{k} {v} (\"{}\")", shortened(example)),
                    None => format!("{k} {v}"),
                })
                .collect::<Vec<_>>()
                .join(", ")
        };
        let split = match &self.refused_us {
            Some(r) => format!(
                "\n  answered  p50 {:.0}  p99 {:.0}  max {:.0}\n  refused   p50 {:.0}  p99 {:.0}  max {:.0}",
                self.answered_us.p50, self.answered_us.p99, self.answered_us.max, r.p50, r.p99, r.max
            ),
            None => String::new(),
        };
        let intervals: String = self
            .intervals
            .iter()
            .map(|i| {
                format!(
                    "\n  from {:>6.0} s  {:>8} requests  {:>6} refused  p50 {:.0}  p99 {:.0}",
                    i.start_s, i.requests, i.refused, i.latency_us.p50, i.latency_us.p99
                )
            })
            .collect();
        let client_cpu = self.client_cpu_us.map_or(String::new(), |us| {
            format!("\nclient CPU  {us:.0} µs per request (this process, user and system)")
        });
        let gpu = self.gpu.as_ref().map_or(String::new(), |g| {
            format!(
                "\ngpu µs      p50 queue {:.0}  submit {:.0}  wait {:.0}  copy {:.0}  ({:.1} requests per dispatch)",
                g.queue_us.p50, g.submit_us.p50, g.wait_us.p50, g.copy_us.p50, g.requests_per_dispatch
            )
        });
        let steal = self.steal_percent.map_or(String::new(), |p| {
            format!("\nhost        {p:.1} % of this machine's CPU time went to other guests (steal)")
        });
        format!(
            "target      {}\nmodel       {} ({}, {} grasper(s), concurrency {}, offered {})\n\
             requests    {} in {:.1} s = {:.0}/s\n\
             latency µs  p50 {:.0}  p90 {:.0}  p99 {:.0}  p99.9 {:.0}  max {:.0}  mean {:.0}{split}{intervals}\n\
             server µs   p50 {:.0}  p99 {:.0}  (prior p50 {:.0}; waiting for a compute thread p50 {:.0}){gpu}\n\
             generator   p50 {:.0}  p99 {:.0} µs after the due time\n\
             outside     p50 {:.0} µs: latency − server − generator (client and transport){client_cpu}\n\
             errors      {}{steal}",
            self.target,
            self.model,
            self.mode,
            self.graspers,
            self.concurrency,
            rate,
            self.requests,
            self.duration_s,
            self.throughput_rps,
            l.p50,
            l.p90,
            l.p99,
            l.p999,
            l.max,
            l.mean,
            s.p50,
            s.p99,
            self.server_prior_us.p50,
            self.server_queue_us.p50,
            self.generator_us.p50,
            self.generator_us.p99,
            (l.p50 - s.p50 - self.generator_us.p50).max(0.0),
            errors
        )
    }
}

/// The first line of `message`, at most 120 characters: enough to say what went wrong in a table.
fn shortened(message: &str) -> String {
    let line = message.lines().next().unwrap_or_default();
    match line.char_indices().nth(120) {
        Some((end, _)) => format!("{}…", &line[..end]),
        None => line.to_owned(),
    }
}
