//! `nak datagen`: a dataset from the paper's distribution with finite-element ground truth.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use nak::data::dataset::{DatasetInfo, SPLIT_RULE, SolverLimits};
use nak::data::generate::{NonlinearTally, Part, generate_linear, generate_nonlinear};
use nak::data::shard::{ChunkRange, Shard};
use nak::engine::Regime;
use nak::fem::nonlinear::{Elimination, NewtonOptions};
use nak::fem::preload::Preloaded;
use nak::fem::{GreenFunctions, Stiffness};
use nak::mesh::TetMesh;

#[derive(clap::Args)]
pub struct DatagenArgs {
    /// A model directory or an .msh file [default: the embedded phantom liver].
    #[arg(long)]
    pub mesh: Option<PathBuf>,
    #[arg(long, value_enum, default_value_t = Regime::Linear)]
    regime: Regime,
    /// Sizes: `paper` (5,000 single-grasper + 5,400 multi-grasper samples) or `tiny` (12 + 8).
    #[arg(long, value_enum, default_value_t = Preset::Paper)]
    preset: Preset,
    /// Single-grasper samples (overrides the preset).
    #[arg(long)]
    single: Option<usize>,
    /// Two-grasper samples (overrides the preset).
    #[arg(long)]
    multi: Option<usize>,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output directory; an interrupted run resumes when started again with the same arguments.
    #[arg(long)]
    out: PathBuf,
    /// Samples per chunk file.
    #[arg(long, default_value_t = 100)]
    chunk_size: usize,
    /// Nonlinear: Newton iterations allowed per load step before the step is cut.
    #[arg(long, default_value_t = NewtonOptions::default().max_iterations)]
    max_newton_iterations: usize,
    /// Nonlinear: load-step halvings allowed before a sample is recorded as failed.
    #[arg(long, default_value_t = NewtonOptions::default().max_step_cuts)]
    max_step_cuts: usize,
    /// Nonlinear: load steps before the last end at this residual, relative to the load (the last
    /// one at 1e-6); looser means fewer Newton iterations on the way.
    #[arg(long, default_value_t = NewtonOptions::default().intermediate_tolerance)]
    intermediate_tolerance: f64,
    /// Nonlinear: rings of nodes around the graspers solved alone after every global Newton step
    /// (nonlinear elimination; 0 solves every node only globally).
    #[arg(long, default_value_t = Elimination::default().rings)]
    elimination_rings: usize,
    /// Nonlinear, with elimination: the first load step, as a fraction of the grasp.
    #[arg(long, default_value_t = Elimination::default().initial_step)]
    elimination_step: f64,
    /// Nonlinear: no load step longer than this fraction of the grasp (0.02: the quasi-static
    /// path's own equilibrium where a grasp has several, at about four times the cost).
    #[arg(long, default_value_t = NewtonOptions::default().max_load_step)]
    max_load_step: f64,
    /// Make only shard I of N (0-based): the chunks c with c mod N = I, in a directory of its own
    /// (--out); `nak dataset join` assembles the N shard directories into the whole dataset.
    #[arg(long, value_name = "I/N")]
    shard: Option<Shard>,
    /// Make only chunks FIRST to LAST (0-based, both included; or one chunk N) of the set, in --out:
    /// part of a set made on another machine with the same arguments, its chunks copied in beside the
    /// others; a run without --chunks makes whatever is left.
    #[arg(long, value_name = "FIRST-LAST")]
    chunks: Option<ChunkRange>,
    /// Where the Green's functions and the gravity preload are cached [default: $NAK_CACHE_DIR, else $XDG_CACHE_HOME/nak or ~/.cache/nak].
    #[arg(long)]
    pub cache_dir: Option<PathBuf>,
}

impl DatagenArgs {
    /// The arguments `words` would give on the command line, for commands that make a dataset as
    /// one of their stages (`nak organ new`).
    pub fn from_words(words: &[String]) -> anyhow::Result<Self> {
        #[derive(clap::Parser)]
        struct Datagen {
            #[command(flatten)]
            args: DatagenArgs,
        }
        let line = std::iter::once("nak datagen".to_owned()).chain(words.iter().cloned());
        Ok(<Datagen as clap::Parser>::try_parse_from(line)?.args)
    }
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum Preset {
    Paper,
    Tiny,
}

pub fn run(args: DatagenArgs, mesh: &TetMesh, cache: PathBuf) -> anyhow::Result<()> {
    let (single, multi) = match args.preset {
        Preset::Paper => (5_000, 5_400),
        Preset::Tiny => (12, 8),
    };
    for (flag, fraction) in [
        ("--elimination-step", args.elimination_step),
        ("--max-load-step", args.max_load_step),
    ] {
        anyhow::ensure!(
            fraction > 0.0 && fraction <= 1.0,
            "{flag} {fraction} is not a fraction of the grasp: give a number in (0, 1]"
        );
    }
    let elimination = (args.elimination_rings > 0).then_some(Elimination {
        rings: args.elimination_rings,
        initial_step: args.elimination_step,
    });
    let info = DatasetInfo {
        mesh_name: mesh.config.name.clone(),
        mesh_hash: mesh.content_hash.clone(),
        node_count: mesh.node_count(),
        regime: args.regime.name().into(),
        seed: args.seed,
        single: args.single.unwrap_or(single),
        multi: args.multi.unwrap_or(multi),
        chunk_size: args.chunk_size.max(1),
        split_rule: SPLIT_RULE.into(),
        made_by: format!("nak {} datagen", env!("CARGO_PKG_VERSION")),
        solver: matches!(args.regime, Regime::Nonlinear).then_some(SolverLimits {
            max_newton_iterations: args.max_newton_iterations,
            max_step_cuts: args.max_step_cuts,
            intermediate_tolerance: args.intermediate_tolerance,
            elimination,
            max_load_step: args.max_load_step,
        }),
        volumetric_law: matches!(args.regime, Regime::Nonlinear).then_some(mesh.config.volumetric_law),
        shard: args.shard,
    };
    if let Some(range) = args.chunks {
        range.check_within(info.chunks()).map_err(anyhow::Error::msg)?;
    }
    let part = Part {
        dir: &args.out,
        chunks: args.chunks,
    };
    let rate = Arc::new(MeanRate::default());
    let shown = Arc::clone(&rate);
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template("{msg} {bar:30} {pos}/{len} ({per_sec}, ETA {mean_eta})")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .with_key(
                "mean_eta",
                move |state: &indicatif::ProgressState, w: &mut dyn std::fmt::Write| {
                    let left = shown.time_left(state.pos() as usize, state.len().unwrap_or(0) as usize);
                    let _ = write!(w, "{}", indicatif::HumanDuration(left));
                },
            ),
    );
    let started = Instant::now();
    // Written to a file or a pipe (a long run in the background), the bar is hidden: a line per
    // percent says how far the run is instead.
    let terminal = std::io::stderr().is_terminal();
    let logged = AtomicUsize::new(usize::MAX);
    let update = |done: usize, total: usize| {
        rate.observe(done, total);
        bar.set_length(total as u64);
        bar.set_position(done as u64);
        let percent = 100 * done / total.max(1);
        if !terminal && logged.swap(percent, Ordering::Relaxed) != percent {
            eprintln!(
                "{}: {done}/{total} ({percent} %), {} elapsed, ETA {}",
                bar.message(),
                indicatif::HumanDuration(started.elapsed()),
                indicatif::HumanDuration(rate.time_left(done, total))
            );
        }
    };
    let generated = match args.regime {
        Regime::Linear => {
            bar.set_message("Green's functions");
            let green = GreenFunctions::load_or_compute(mesh, Stiffness::Linear, &cache, update)
                .with_context(|| format!("cannot prepare the Green's functions (cache {})", cache.display()))?;
            bar.set_message("samples");
            bar.set_position(0);
            generate_linear(mesh, &green, &info, part, update)?
        }
        Regime::Nonlinear => {
            bar.set_message("gravity preload (one Newton solve, cached)");
            bar.enable_steady_tick(std::time::Duration::from_millis(200));
            let options = NewtonOptions {
                max_iterations: args.max_newton_iterations,
                max_step_cuts: args.max_step_cuts,
                intermediate_tolerance: args.intermediate_tolerance,
                elimination,
                max_load_step: args.max_load_step,
                ..NewtonOptions::default()
            };
            let preloaded = Preloaded::load_or_compute(mesh, &cache, options)
                .with_context(|| format!("cannot solve the gravity preload (cache {})", cache.display()))?;
            if let Some(solved) = &preloaded.solved {
                bar.println(format!(
                    "gravity preload: {} load steps, {} Newton iterations, {:.1} s; cached in {}",
                    solved.stats.load_steps,
                    solved.stats.newton_iterations,
                    solved.seconds,
                    preloaded.path.display()
                ));
            }
            bar.set_message("samples");
            bar.set_position(0);
            generate_nonlinear(mesh, &preloaded, &info, part, update)?
        }
    };
    bar.finish_and_clear();
    let seconds = started.elapsed().as_secs_f64();
    let new = generated
        .samples
        .saturating_sub(generated.chunks_skipped * info.chunk_size);
    let part = match (info.shard, args.chunks) {
        (Some(shard), _) => format!(" (shard {shard} of a dataset of {} samples)", info.total()),
        (None, Some(range)) => format!(" (chunks {range} of a dataset of {} samples)", info.total()),
        (None, None) => format!(" ({} single, {} multi)", info.single, info.multi),
    };
    println!(
        "{}: {} samples{part} in {} chunks ({} resumed); {:.1} s, {:.1} samples/s",
        args.out.display(),
        generated.samples,
        generated.chunks_written + generated.chunks_skipped,
        generated.chunks_skipped,
        seconds,
        new as f64 / seconds.max(1e-9),
    );
    match args.regime {
        Regime::Linear => println!("{} direct solves", generated.direct_solves),
        Regime::Nonlinear => print_nonlinear_tally(&generated.nonlinear),
    }
    Ok(())
}

/// Time left at this run's mean rate. indicatif's own estimate follows the last few samples, and one
/// slow grasp (a minute where most take two seconds) sends it to days; chunks resumed from an earlier
/// run, counted done at the start, are not part of the rate.
#[derive(Default)]
struct MeanRate {
    /// When this stage's first progress came, how much was done then, and the stage's total.
    since: Mutex<Option<(Instant, usize, usize)>>,
}

impl MeanRate {
    fn observe(&self, done: usize, total: usize) {
        let Ok(mut since) = self.since.lock() else { return };
        // A new stage (Green's functions, then samples) starts its own count.
        if !matches!(*since, Some((_, first, stage)) if stage == total && done >= first) {
            *since = Some((Instant::now(), done, total));
        }
    }

    fn time_left(&self, done: usize, total: usize) -> Duration {
        let Some((start, first, _)) = self.since.lock().ok().and_then(|since| *since) else {
            return Duration::ZERO;
        };
        let made = done.saturating_sub(first);
        if made == 0 {
            return Duration::ZERO;
        }
        start.elapsed().mul_f64(total.saturating_sub(done) as f64 / made as f64)
    }
}

/// The solver's effort in this run: time per sample over every sample attempted (what a dataset
/// costs), iterations and factorizations over the converged ones (a failed solve reports none).
fn print_nonlinear_tally(t: &NonlinearTally) {
    if t.attempted == 0 {
        println!("nonlinear: every chunk was already complete; nothing solved in this run");
        return;
    }
    let converged = t.attempted - t.failed;
    let per_converged = |v: usize| v as f64 / converged.max(1) as f64;
    let mut seconds = t.solve_seconds.clone();
    seconds.sort_by(f64::total_cmp);
    let median = seconds.get(seconds.len() / 2).copied().unwrap_or(0.0);
    let mean = seconds.iter().sum::<f64>() / t.attempted.max(1) as f64;
    println!(
        "nonlinear: {} samples, {} failed ({:.1} %); per sample on one core {:.2} s median / {:.2} s mean / {:.2} s \
         for the slowest 1 % / {:.2} s slowest; per converged sample: Newton iterations {:.1} mean / {} max, load steps {:.1} mean, \
         factorizations {:.1} mean, conjugate-gradient iterations {:.1} mean, local Newton iterations around the \
         graspers {:.1} mean; {} with step cuts, {} with shifted tangents, {} load steps undone for jumping branches; \
         {} load-path states kept beside the chunks (each converged sample's load steps before its last)",
        t.attempted,
        t.failed,
        100.0 * t.failed as f64 / t.attempted.max(1) as f64,
        median,
        mean,
        seconds.get(seconds.len() * 99 / 100).copied().unwrap_or(0.0),
        seconds.last().copied().unwrap_or(0.0),
        per_converged(t.newton_iterations),
        t.max_newton_iterations,
        per_converged(t.load_steps),
        per_converged(t.factorizations),
        per_converged(t.krylov_iterations),
        per_converged(t.local_iterations),
        t.cut,
        t.shifted,
        t.branch_jumps,
        t.load_steps - converged,
    );
    if !t.failure_reasons.is_empty() {
        let reasons: Vec<String> = t.failure_reasons.iter().map(|(why, n)| format!("{n} {why}")).collect();
        println!("failed because: {}", reasons.join("; "));
    }
    let p = &t.profile;
    let total: f64 = seconds.iter().sum::<f64>().max(1e-9);
    let share = |d: std::time::Duration| 100.0 * d.as_secs_f64() / total;
    let stages = p.assembly + p.factorization + p.linear_solve + p.line_search + p.elimination;
    let failed = 100.0 * t.failed_seconds / total;
    println!(
        "time: assembly {:.0} %, factorization {:.0} %, linear solves {:.0} %, line search {:.0} %, graspers' \
         neighbourhood {:.0} %, failed samples {failed:.0} %, other {:.0} %",
        share(p.assembly),
        share(p.factorization),
        share(p.linear_solve),
        share(p.line_search),
        share(p.elimination),
        (100.0 - share(stages) - failed).max(0.0),
    );
}
