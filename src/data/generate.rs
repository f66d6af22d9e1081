//! `nak datagen --regime linear`: samples from p with linear finite-element ground truth.

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;

use super::GraspSampler;
use super::dataset::{self, DatasetError, DatasetInfo, SampleRecord};
use crate::fem::{GreenLinear, solve_dirichlet};
use crate::mesh::TetMesh;
use crate::prior::InteractionPoints;

/// What a generation run did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Generated {
    pub chunks_written: usize,
    pub chunks_skipped: usize,
    pub samples: usize,
    /// Samples whose grasp reached past the precomputed Green's functions, solved directly instead.
    pub direct_solves: usize,
}

/// The exact linear field of one sample: through G when every grasped node has a column (fast),
/// else by a direct Dirichlet solve (one factorization).
fn linear_field(
    mesh: &TetMesh,
    green: &GreenLinear,
    sample: &SampleRecord,
    direct: &AtomicUsize,
) -> Result<Vec<f32>, DatasetError> {
    let mut points = InteractionPoints::default();
    for g in &sample.grasps {
        for &n in &g.nodes {
            points.push(n, mesh.positions[n as usize], g.displacement);
        }
    }
    let mut field = vec![0.0f32; 3 * mesh.node_count()];
    if points.nodes.iter().all(|n| green.candidates().binary_search(n).is_ok()) {
        green
            .solve(&points, None, &mut field)
            .map_err(|e| DatasetError::Solver(e.to_string()))?;
    } else {
        direct.fetch_add(1, Ordering::Relaxed);
        let prescribed: Vec<(u32, [f64; 3])> = points
            .nodes
            .iter()
            .copied()
            .zip(points.displacements.iter().copied())
            .collect();
        let u = solve_dirichlet(mesh, &prescribed)
            .map_err(|e| DatasetError::Solver(format!("sample {}: {e}", sample.index)))?;
        for (dst, src) in field.chunks_exact_mut(3).zip(&u) {
            for k in 0..3 {
                dst[k] = src[k] as f32;
            }
        }
    }
    Ok(field)
}

/// Generates (or resumes) the dataset described by `info` in `dir`; `progress(samples done, total)`.
pub fn generate_linear(
    mesh: &TetMesh,
    green: &GreenLinear,
    info: &DatasetInfo,
    dir: &Path,
    progress: impl Fn(usize, usize) + Sync,
) -> Result<Generated, DatasetError> {
    if let Ok(existing) = dataset::read_info(dir)
        && existing != *info
    {
        return Err(DatasetError::Format {
            path: dir.join("dataset.json").display().to_string(),
            message: format!("holds another dataset ({existing:?}); choose another --out to make {info:?}"),
        });
    }
    dataset::write_info(dir, info)?;
    let sampler = GraspSampler::from_mesh(mesh)?;
    let complete = dataset::complete_chunks(dir, info.chunks());
    let total = info.total();
    let done = AtomicUsize::new(0);
    let direct = AtomicUsize::new(0);
    let mut result = Generated {
        chunks_written: 0,
        chunks_skipped: 0,
        samples: total,
        direct_solves: 0,
    };
    for (chunk, is_complete) in complete.into_iter().enumerate() {
        let range = chunk * info.chunk_size..((chunk + 1) * info.chunk_size).min(total);
        if is_complete {
            result.chunks_skipped += 1;
            done.fetch_add(range.len(), Ordering::Relaxed);
            progress(done.load(Ordering::Relaxed), total);
            continue;
        }
        let samples: Vec<SampleRecord> = range
            .clone()
            .map(|i| dataset::draw(&sampler, info, i as u64))
            .collect::<Result<_, _>>()?;
        let fields: Vec<Vec<f32>> = samples
            .par_iter()
            .map(|s| {
                let f = linear_field(mesh, green, s, &direct);
                progress(done.fetch_add(1, Ordering::Relaxed) + 1, total);
                f
            })
            .collect::<Result<_, _>>()?;
        dataset::write_chunk(dir, chunk, mesh.node_count(), &samples, &fields)?;
        result.chunks_written += 1;
    }
    result.direct_solves = direct.load(Ordering::Relaxed);
    Ok(result)
}
