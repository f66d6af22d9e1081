//! `nak datagen`: samples from p with finite-element ground truth, linear or nonlinear.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;

use super::GraspSampler;
use super::dataset::{self, DatasetError, DatasetInfo, PathField, SampleRecord, SolveRecord};
use super::shard::ChunkRange;
use crate::fem::nonlinear::{PathState, SolveProfile, SolveStats};
use crate::fem::preload::Preloaded;
use crate::fem::{FemError, GreenFunctions, nodal_forces, solve_dirichlet};
use crate::mesh::TetMesh;
use crate::prior::InteractionPoints;

/// What a generation run did (counts cover the samples solved in this run, not resumed chunks).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Generated {
    pub chunks_written: usize,
    pub chunks_skipped: usize,
    pub samples: usize,
    /// Linear: samples whose grasp reached past the precomputed Green's functions, solved directly.
    pub direct_solves: usize,
    /// Nonlinear: solver effort summed over the samples attempted, and how many needed step cuts or failed.
    pub nonlinear: NonlinearTally,
}

#[derive(Debug, Clone, Default, PartialEq)]
pub struct NonlinearTally {
    /// Samples whose solve ran in this run, converged or failed.
    pub attempted: usize,
    pub newton_iterations: usize,
    pub load_steps: usize,
    pub cut: usize,
    pub failed: usize,
    /// Failed samples by why their last load step failed (inverted elements, Newton stalls, …).
    pub failure_reasons: BTreeMap<String, usize>,
    pub shifted: usize,
    pub factorizations: usize,
    pub krylov_iterations: usize,
    pub local_iterations: usize,
    /// Load steps undone because they jumped to another equilibrium branch.
    pub branch_jumps: usize,
    /// Per-sample solve times (s), failed ones included, in the order the samples finished: their
    /// sum divided by `attempted` is the cost of one sample on one core.
    pub solve_seconds: Vec<f64>,
    pub max_newton_iterations: usize,
    /// Where the converged samples' time went (a failed solve reports no profile).
    pub profile: SolveProfile,
    /// The failed samples' solve time (s): every load-step cut they tried.
    pub failed_seconds: f64,
}

impl NonlinearTally {
    fn add(&mut self, stats: &SolveStats, profile: &SolveProfile, failure: Option<&str>, seconds: f64) {
        self.attempted += 1;
        self.factorizations += stats.factorizations;
        self.krylov_iterations += stats.krylov_iterations;
        self.local_iterations += stats.local_iterations;
        self.branch_jumps += stats.branch_jumps;
        self.profile.add(profile);
        self.newton_iterations += stats.newton_iterations;
        self.load_steps += stats.load_steps;
        self.cut += usize::from(stats.step_cuts > 0);
        if let Some(reason) = failure {
            self.failed += 1;
            self.failed_seconds += seconds;
            *self.failure_reasons.entry(reason.to_owned()).or_default() += 1;
        }
        self.shifted += usize::from(stats.shifted_factorizations > 0);
        self.solve_seconds.push(seconds);
        self.max_newton_iterations = self.max_newton_iterations.max(stats.newton_iterations);
    }
}

/// The exact linear field of one sample, and its grasps' forces: through G when every grasped node
/// has a column (fast), else by a direct Dirichlet solve (one factorization) and K·u.
fn linear_field(
    mesh: &TetMesh,
    green: &GreenFunctions,
    sample: &mut SampleRecord,
    direct: &AtomicUsize,
) -> Result<Vec<f32>, DatasetError> {
    let prescribed = sample.prescribed();
    let mut points = InteractionPoints::default();
    for &(n, u) in &prescribed {
        points.push(n, mesh.positions[n as usize], u);
    }
    let mut field = vec![0.0f32; 3 * mesh.node_count()];
    let mut forces = Vec::with_capacity(points.len());
    let solver_error = |e: &dyn std::fmt::Display| DatasetError::Solver(format!("sample {}: {e}", sample.index));
    if points.nodes.iter().all(|n| green.candidates().binary_search(n).is_ok()) {
        green
            .solve(&points.nodes, &points.displacements, None, &mut field, &mut forces)
            .map_err(|e| solver_error(&e))?;
    } else {
        direct.fetch_add(1, Ordering::Relaxed);
        let u = solve_dirichlet(mesh, &prescribed).map_err(|e| solver_error(&e))?;
        write_field(&mut field, &u);
        forces = nodal_forces(mesh, &u, &points.nodes).map_err(|e| solver_error(&e))?;
    }
    sample.set_forces(|n| force_of(&points.nodes, &forces, n));
    Ok(field)
}

/// The force on `node` from per-point forces listed in the order of `nodes`.
fn force_of(nodes: &[u32], forces: &[[f64; 3]], node: u32) -> [f64; 3] {
    nodes.iter().position(|&m| m == node).map_or([0.0; 3], |i| forces[i])
}

/// One sample's ground truth: its field and, for a nonlinear solve, the converged states of its
/// load steps before the last.
struct Solved {
    field: Vec<f32>,
    path: Vec<PathField>,
}

impl From<Vec<f32>> for Solved {
    fn from(field: Vec<f32>) -> Self {
        Self {
            field,
            path: Vec::new(),
        }
    }
}

fn write_field(field: &mut [f32], u: &[[f64; 3]]) {
    for (dst, src) in field.chunks_exact_mut(3).zip(u) {
        for k in 0..3 {
            dst[k] = src[k] as f32;
        }
    }
}

/// Generates (or resumes) a linear dataset; `progress(samples done, total)`.
pub fn generate_linear(
    mesh: &TetMesh,
    green: &GreenFunctions,
    info: &DatasetInfo,
    part: Part<'_>,
    progress: impl Fn(usize, usize) + Sync,
) -> Result<Generated, DatasetError> {
    let direct = AtomicUsize::new(0);
    let mut generated = generate(mesh, info, part, progress, |sample| {
        linear_field(mesh, green, sample, &direct).map(Solved::from)
    })?;
    generated.direct_solves = direct.load(Ordering::Relaxed);
    Ok(generated)
}

/// Generates (or resumes) a nonlinear dataset from the gravity-preloaded state. A sample whose solve
/// fails is kept with a NaN field and its failure report; the run goes on.
pub fn generate_nonlinear(
    mesh: &TetMesh,
    preloaded: &Preloaded,
    info: &DatasetInfo,
    part: Part<'_>,
    progress: impl Fn(usize, usize) + Sync,
) -> Result<Generated, DatasetError> {
    let tally = Mutex::new(NonlinearTally::default());
    let mut generated = generate(mesh, info, part, progress, |sample| {
        let started = std::time::Instant::now();
        let mut field = vec![f32::NAN; 3 * mesh.node_count()];
        let prescribed = sample.prescribed();
        let mut profile = SolveProfile::default();
        let mut failure_reason = None;
        let mut path = Vec::new();
        let record = match preloaded.grasp(&prescribed) {
            Ok(equilibrium) => {
                profile = equilibrium.profile;
                write_field(&mut field, &equilibrium.displacement);
                path = path_fields(sample.index, &equilibrium.path);
                let held: Vec<u32> = prescribed.iter().map(|&(n, _)| n).collect();
                sample.set_forces(|n| force_of(&held, &equilibrium.reactions, n));
                SolveRecord {
                    stats: equilibrium.stats,
                    failure: None,
                }
            }
            Err(e) => {
                tracing::warn!(sample = sample.index, "nonlinear solve failed: {e}");
                failure_reason = Some(match &e {
                    FemError::NotConverged { reason, .. } => reason.clone(),
                    other => other.to_string(),
                });
                SolveRecord {
                    stats: SolveStats::default(),
                    failure: Some(e.to_string()),
                }
            }
        };
        if let Ok(mut t) = tally.lock() {
            t.add(
                &record.stats,
                &profile,
                failure_reason.as_deref(),
                started.elapsed().as_secs_f64(),
            );
        }
        sample.solver = Some(record);
        Ok(Solved { field, path })
    })?;
    generated.nonlinear = tally.into_inner().unwrap_or_default();
    Ok(generated)
}

fn path_fields(sample: u64, path: &[PathState]) -> Vec<PathField> {
    path.iter()
        .map(|state| {
            let mut field = vec![0.0; 3 * state.displacement.len()];
            write_field(&mut field, &state.displacement);
            PathField {
                sample,
                load: state.load,
                field,
            }
        })
        .collect()
}

/// Where a run writes its set and which of the set's chunks it makes (None: all it owns).
#[derive(Debug, Clone, Copy)]
pub struct Part<'a> {
    pub dir: &'a Path,
    pub chunks: Option<ChunkRange>,
}

/// The chunked, resumable driver both regimes share: draws each chunk's samples from (seed, index),
/// solves them in parallel over cores with `solve`, writes the chunk. A shard does its chunks only,
/// and a run given a chunk range only those of them.
fn generate(
    mesh: &TetMesh,
    info: &DatasetInfo,
    part: Part<'_>,
    progress: impl Fn(usize, usize) + Sync,
    solve: impl Fn(&mut SampleRecord) -> Result<Solved, DatasetError> + Sync,
) -> Result<Generated, DatasetError> {
    let dir = part.dir;
    if let Ok(existing) = dataset::read_info(dir)
        && existing != *info
    {
        return Err(DatasetError::Format {
            path: dir.join("dataset.json").display().to_string(),
            message: format!(
                "holds another dataset ({}); resume it with its own arguments or choose another --out",
                dataset::differences(&existing, info)
            ),
        });
    }
    dataset::write_info(dir, info)?;
    dataset::write_mesh(dir, mesh)?;
    let sampler = GraspSampler::from_mesh(mesh)?;
    let complete = dataset::complete_chunks(dir, info.chunks());
    let range_of = |chunk: usize| chunk * info.chunk_size..((chunk + 1) * info.chunk_size).min(info.total());
    let owned = |chunk: &usize| {
        info.shard.is_none_or(|shard| shard.owns(*chunk)) && part.chunks.is_none_or(|range| range.contains(*chunk))
    };
    let total = (0..info.chunks()).filter(owned).map(|c| range_of(c).len()).sum();
    let done = AtomicUsize::new(0);
    let mut result = Generated {
        samples: total,
        ..Generated::default()
    };
    let mut pending = Vec::new();
    for (chunk, is_complete) in complete.into_iter().enumerate().filter(|(c, _)| owned(c)) {
        if is_complete {
            result.chunks_skipped += 1;
            done.fetch_add(range_of(chunk).len(), Ordering::Relaxed);
        } else {
            pending.push(chunk);
        }
    }
    // Where this run starts: what earlier runs made counts as done but not towards its rate.
    progress(done.load(Ordering::Relaxed), total);
    // Chunks run side by side as well as their samples: a core that has finished its part of one
    // chunk starts the next instead of waiting for the chunk's slowest sample (nonlinear samples vary
    // from a second to a minute). Each chunk is written when its own samples are done.
    pending.par_iter().with_max_len(1).try_for_each(|&chunk| {
        let mut samples: Vec<SampleRecord> = range_of(chunk)
            .map(|i| dataset::draw(&sampler, info, i as u64))
            .collect::<Result<_, _>>()?;
        let solved: Vec<Solved> = samples
            .par_iter_mut()
            .with_max_len(1)
            .map(|s| {
                let f = solve(s);
                progress(done.fetch_add(1, Ordering::Relaxed) + 1, total);
                f
            })
            .collect::<Result<_, _>>()?;
        let (fields, paths): (Vec<Vec<f32>>, Vec<Vec<PathField>>) =
            solved.into_iter().map(|s| (s.field, s.path)).unzip();
        let states: Vec<PathField> = paths.into_iter().flatten().collect();
        if !states.is_empty() {
            dataset::write_path_states(dir, chunk, mesh.node_count(), &states)?;
        }
        dataset::write_chunk(dir, chunk, mesh.node_count(), &samples, &fields)
    })?;
    result.chunks_written = pending.len();
    Ok(result)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A failed solve reports no profile: its whole time is counted apart, so that `nak datagen`
    /// can say how much of a run the failures took instead of leaving it unexplained.
    #[test]
    fn a_failed_samples_time_is_counted_apart() {
        let mut tally = NonlinearTally::default();
        let converged = SolveStats {
            newton_iterations: 10,
            ..SolveStats::default()
        };
        tally.add(&converged, &SolveProfile::default(), None, 1.5);
        let reason = "Newton did not converge in the allowed iterations";
        tally.add(&SolveStats::default(), &SolveProfile::default(), Some(reason), 30.0);
        assert_eq!((tally.attempted, tally.failed), (2, 1));
        assert_eq!(tally.failed_seconds, 30.0);
        assert_eq!(tally.solve_seconds, vec![1.5, 30.0]);
        assert_eq!(tally.failure_reasons.get(reason), Some(&1));
    }
}
