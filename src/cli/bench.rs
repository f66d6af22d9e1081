//! `nak bench`: run a load test with a live progress line, print the summary, write the JSON report.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use nak::bench::{self, BenchConfig, Mode};
use nak::cpu_idle::PollingIdle;

use super::connect::ConnectArgs;

#[derive(clap::Args)]
pub struct BenchArgs {
    #[command(flatten)]
    connection: ConnectArgs,
    /// Model to request.
    #[arg(long, default_value = "kelvinlet")]
    model: String,
    #[arg(long, value_enum, default_value_t = ModeArg::Unary)]
    mode: ModeArg,
    /// Workers (unary) or streams (stream mode), each with its own connection.
    #[arg(long, default_value_t = 4)]
    concurrency: usize,
    /// Offered load in requests/s over all workers (open loop, latency from the due time), or "max"
    /// (closed loop: each worker sends when its last answer arrives).
    #[arg(long, default_value = "max", value_parser = parse_rate)]
    rate: Rate,
    /// Measured time: "10s", "500ms", "2m" or seconds.
    #[arg(long, default_value = "10s", value_parser = parse_duration)]
    duration: Duration,
    /// Load sent before measuring.
    #[arg(long, default_value = "1s", value_parser = parse_duration)]
    warmup: Duration,
    /// Graspers per request, drawn from the paper's distribution p over the server's mesh.
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u64).range(1..=2))]
    graspers: u64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Distinct requests drawn and cycled through.
    #[arg(long, default_value_t = 1024)]
    distinct_requests: usize,
    /// Also report percentiles per interval of this length ("1m", "10s"): latency over time.
    #[arg(long, value_parser = parse_duration)]
    interval: Option<Duration>,
    /// Write the report as JSON here.
    #[arg(long)]
    output: Option<PathBuf>,
    /// Keep this machine's idle CPUs polling instead of halting during the test (as `nak serve
    /// --poll-idle-cpus` does; needs root): for a load generator on a machine of its own, whose
    /// wake-ups on each answer would otherwise count as the server's latency.
    #[arg(long)]
    poll_idle_cpus: bool,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum ModeArg {
    Unary,
    Stream,
}

#[derive(Clone, Copy, Debug)]
pub struct Rate(Option<f64>);

fn parse_rate(text: &str) -> Result<Rate, String> {
    if text == "max" {
        return Ok(Rate(None));
    }
    match text.parse::<f64>() {
        Ok(r) if r > 0.0 && r.is_finite() => Ok(Rate(Some(r))),
        _ => Err(format!("{text:?} is not a positive rate in requests/s or \"max\"")),
    }
}

fn parse_duration(text: &str) -> Result<Duration, String> {
    let (number, scale) = if let Some(n) = text.strip_suffix("ms") {
        (n, 1e-3)
    } else if let Some(n) = text.strip_suffix('s') {
        (n, 1.0)
    } else if let Some(n) = text.strip_suffix('m') {
        (n, 60.0)
    } else {
        (text, 1.0)
    };
    match number.trim().parse::<f64>() {
        Ok(v) if v >= 0.0 && v.is_finite() => Ok(Duration::from_secs_f64(v * scale)),
        _ => Err(format!("{text:?} is not a duration such as 10s, 500ms or 2m")),
    }
}

pub fn run(args: BenchArgs) -> anyhow::Result<()> {
    let _idle_polling = args.poll_idle_cpus.then(PollingIdle::request).transpose()?;
    let config = BenchConfig {
        connection: args.connection.config(),
        model: args.model,
        mode: match args.mode {
            ModeArg::Unary => Mode::Unary,
            ModeArg::Stream => Mode::Stream,
        },
        concurrency: args.concurrency,
        rate: args.rate.0,
        duration: args.duration,
        warmup: args.warmup,
        graspers: args.graspers as usize,
        seed: args.seed,
        distinct_requests: args.distinct_requests,
        interval: args.interval,
    };
    let total = (config.warmup + config.duration).as_millis() as u64;
    let bar = ProgressBar::new(total).with_style(
        ProgressStyle::with_template("{spinner} [{bar:30}] {msg}")
            .map(|s| s.progress_chars("=> "))
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    // One thread runs every connection: a request and its answer are never handed between the
    // load generator's own threads, each hand-off a wake-up whose delay would count as the server's.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let report = runtime.block_on(bench::run(&config, |p| {
        bar.set_position(p.elapsed.as_millis() as u64);
        let seconds = p.elapsed.as_secs_f64().max(1e-3);
        bar.set_message(format!(
            "{:.1}/{:.0} s  {} answers ({:.0}/s)  p50 {:.0} µs  p99 {:.0} µs  errors {}",
            p.elapsed.as_secs_f64(),
            p.total.as_secs_f64(),
            p.completed,
            p.completed as f64 / seconds,
            p.p50_us,
            p.p99_us,
            p.errors
        ));
    }))?;
    bar.finish_and_clear();
    println!("{}", report.table());
    if let Some(path) = args.output {
        let json = serde_json::to_string_pretty(&report)?;
        std::fs::write(&path, json + "\n").with_context(|| format!("cannot write {}", path.display()))?;
        println!("report      {}", path.display());
    }
    Ok(())
}
