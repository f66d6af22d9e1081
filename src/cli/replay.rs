//! `nak replay`: re-send a recording's requests to a server, report latency and how far the answers
//! moved from what was recorded.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;
use hdrhistogram::Histogram;
use nak::bench::Percentiles;
use nak::record::replay;
use serde::Serialize;

use super::connect::ConnectArgs;

#[derive(clap::Args)]
pub struct ReplayArgs {
    /// A recording made by `nak serve --record` (a file cut short by a hard kill is read up to its
    /// last complete chunk).
    file: PathBuf,
    #[command(flatten)]
    connection: ConnectArgs,
    /// `recorded`: keep the recorded spacing between requests; `max`: send each as soon as the last
    /// was answered.
    #[arg(long, value_enum, default_value_t = Pace::Recorded)]
    pace: Pace,
    /// Compare every answer with the recorded one (the rows the recording holds).
    #[arg(long)]
    compare: bool,
    /// Write the summary as JSON here.
    #[arg(long)]
    output: Option<PathBuf>,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum Pace {
    Recorded,
    Max,
}

#[derive(Serialize)]
struct Summary {
    file: String,
    exchanges: usize,
    truncated: Option<String>,
    latency_us: Option<Percentiles>,
    /// Answers whose status differs from the recorded one.
    status_mismatches: usize,
    /// Over all compared answers, metres.
    largest_difference_m: Option<f32>,
    compared: usize,
}

pub fn run(args: ReplayArgs) -> anyhow::Result<()> {
    let recording = replay::read(&args.file)?;
    if let Some(reason) = &recording.truncated {
        eprintln!(
            "{}: ends mid-record ({reason}); read the {} exchanges before it",
            args.file.display(),
            recording.exchanges.len()
        );
    }
    let runtime = tokio::runtime::Runtime::new().context("cannot start the async runtime")?;
    let summary = runtime.block_on(async {
        let mut client = nak::client::connect(&args.connection.config()).await?;
        let mut latency = Histogram::<u64>::new_with_bounds(1, 100_000_000, 3)?;
        let (mut mismatches, mut compared, mut largest) = (0usize, 0usize, None::<f32>);
        let start = Instant::now();
        let first = recording.exchanges.first().map_or(0, |e| e.log_time);
        for exchange in &recording.exchanges {
            if let Pace::Recorded = args.pace {
                let due = start + Duration::from_nanos(exchange.log_time.saturating_sub(first));
                tokio::time::sleep_until(due.into()).await;
            }
            let sent = Instant::now();
            let answer = client.predict(exchange.request.clone()).await;
            latency.saturating_record(sent.elapsed().as_micros().max(1) as u64);
            let recorded_ok = exchange.response.as_ref().is_some_and(|r| r.error.is_none());
            match (&answer, &exchange.response) {
                (Ok(new), Some(old)) if args.compare => {
                    if let Some(d) = replay::largest_difference(old, new.get_ref()) {
                        compared += 1;
                        largest = Some(largest.map_or(d, |l| l.max(d)));
                    }
                }
                (Err(_), _) if recorded_ok => mismatches += 1,
                (Ok(_), None) => mismatches += 1,
                _ => {}
            }
        }
        anyhow::Ok(Summary {
            file: args.file.display().to_string(),
            exchanges: recording.exchanges.len(),
            truncated: recording.truncated.clone(),
            latency_us: (!latency.is_empty()).then(|| Percentiles::of(&latency)),
            status_mismatches: mismatches,
            largest_difference_m: largest,
            compared,
        })
    })?;
    println!("replayed    {} exchanges from {}", summary.exchanges, summary.file);
    if let Some(l) = &summary.latency_us {
        println!(
            "latency µs  p50 {:.0}  p90 {:.0}  p99 {:.0}  max {:.0}",
            l.p50, l.p90, l.p99, l.max
        );
    }
    println!("mismatched  {} status(es)", summary.status_mismatches);
    if args.compare {
        match summary.largest_difference_m {
            Some(d) => println!(
                "difference  largest {:.3e} m over {} compared answers",
                d, summary.compared
            ),
            None => println!("difference  nothing to compare (recorded without displacements?)"),
        }
    }
    if let Some(path) = &args.output {
        std::fs::write(path, serde_json::to_string_pretty(&summary)? + "\n")
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(())
}
