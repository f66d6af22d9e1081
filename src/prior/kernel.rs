//! The f32 field kernel: `u(x) = Σ_j s·[(a/r_ε + b/r_ε³) k_j + r (r·k_j)/r_ε³]` over many nodes.
//!
//! Nodes are stored as a structure of arrays, padded to whole blocks of [`BLOCK`] nodes. Each block
//! accumulates its field in registers/L1 over all interaction points, then writes interleaved
//! (N, 3) rows. The block function is compiled for several x86-64 feature levels and picked at run
//! time (AVX-512, AVX2+FMA, SSE4.1, baseline), so one portable binary runs at the speed of the CPU it
//! finds. Blocks are spread over cores for large meshes.

use multiversion::multiversion;
use rayon::prelude::*;

use super::gpu::Resident;
use super::{Coefficients, Kelvinlet};

/// Nodes per block: 64 × 6 f32 arrays stay in L1 and fill whole AVX-512 registers.
pub const BLOCK: usize = 64;

/// Below this many nodes one core is faster than the cost of waking others.
const PARALLEL_MIN_NODES: usize = 4096;

/// Positions of the nodes a field is evaluated at: f32, structure of arrays, in whole blocks (the
/// last one padded with zeros, whose results are never written out).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct NodeCloud {
    len: usize,
    x: Vec<[f32; BLOCK]>,
    y: Vec<[f32; BLOCK]>,
    z: Vec<[f32; BLOCK]>,
    /// Set when the cloud is also uploaded to the GPU: fields are then evaluated there.
    resident: Option<Resident>,
}

impl NodeCloud {
    pub fn new(positions: impl ExactSizeIterator<Item = [f64; 3]>) -> Self {
        let len = positions.len();
        let blocks = len.div_ceil(BLOCK);
        let mut cloud = NodeCloud {
            len,
            x: vec![[0.0; BLOCK]; blocks],
            y: vec![[0.0; BLOCK]; blocks],
            z: vec![[0.0; BLOCK]; blocks],
            resident: None,
        };
        for (i, p) in positions.enumerate() {
            let (b, o) = (i / BLOCK, i % BLOCK);
            cloud.x[b][o] = p[0] as f32;
            cloud.y[b][o] = p[1] as f32;
            cloud.z[b][o] = p[2] as f32;
        }
        cloud
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub fn position(&self, block: usize, offset: usize) -> [f32; 3] {
        [self.x[block][offset], self.y[block][offset], self.z[block][offset]]
    }

    /// Evaluates fields over this cloud on the GPU from now on (the cloud must be uploaded there).
    pub fn make_resident(&mut self, resident: Resident) {
        self.resident = Some(resident);
    }

    /// Where fields over this cloud are evaluated, if on a GPU.
    pub fn resident(&self) -> Option<&Resident> {
        self.resident.as_ref()
    }
}

/// Kernel constants in f32.
#[derive(Clone, Copy)]
struct Constants {
    a: f32,
    b: f32,
    epsilon_sq: f32,
}

impl Kelvinlet {
    /// Writes the field of `coefficients` at every node of `cloud` into `out`, row-major (N, 3);
    /// `out` holds `3 * cloud.len()` values.
    pub fn evaluate(&self, coefficients: &Coefficients, cloud: &NodeCloud, out: &mut [f32]) {
        debug_assert_eq!(
            out.len(),
            3 * cloud.len(),
            "output buffer does not match the node cloud"
        );
        if let Some(r) = &cloud.resident {
            match r.gpu.evaluate(self, r.cloud, coefficients, out) {
                Ok(()) => return,
                // The answer is still owed: the CPU gives the same field, a little later.
                Err(e) => tracing::warn!("GPU prior failed, this request is evaluated on the CPU: {e}"),
            }
        }
        self.evaluate_on_cpu(coefficients, cloud, out);
    }

    /// [`Self::evaluate`] on the CPU whatever the cloud's residence (reference and fallback).
    pub fn evaluate_on_cpu(&self, coefficients: &Coefficients, cloud: &NodeCloud, out: &mut [f32]) {
        let constants = Constants {
            a: self.a as f32,
            b: self.b as f32,
            epsilon_sq: self.epsilon_sq as f32,
        };
        let run = |(block, chunk): (usize, &mut [f32])| {
            field_block(
                &cloud.x[block],
                &cloud.y[block],
                &cloud.z[block],
                coefficients,
                constants,
                chunk,
            );
        };
        if cloud.len >= PARALLEL_MIN_NODES {
            out.par_chunks_mut(3 * BLOCK).enumerate().with_min_len(8).for_each(run);
        } else {
            out.chunks_mut(3 * BLOCK).enumerate().for_each(run);
        }
    }
}

/// One block of nodes: `out` holds up to BLOCK interleaved rows (fewer in the last block).
#[multiversion(targets(
    "x86_64+avx512f+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+sse4.1",
    "aarch64+neon"
))]
fn field_block(
    xs: &[f32; BLOCK],
    ys: &[f32; BLOCK],
    zs: &[f32; BLOCK],
    c: &Coefficients,
    k: Constants,
    out: &mut [f32],
) {
    let mut ux = [0.0f32; BLOCK];
    let mut uy = [0.0f32; BLOCK];
    let mut uz = [0.0f32; BLOCK];
    for j in 0..c.len() {
        let (px, py, pz) = (c.x[j], c.y[j], c.z[j]);
        let (kx, ky, kz) = (c.kx[j], c.ky[j], c.kz[j]);
        for i in 0..BLOCK {
            let rx = xs[i] - px;
            let ry = ys[i] - py;
            let rz = zs[i] - pz;
            let r_sq = rx * rx + ry * ry + rz * rz + k.epsilon_sq;
            let inv = 1.0 / r_sq.sqrt();
            let inv3 = inv * inv * inv;
            let diagonal = k.a * inv + k.b * inv3;
            let along = (rx * kx + ry * ky + rz * kz) * inv3;
            ux[i] += diagonal * kx + along * rx;
            uy[i] += diagonal * ky + along * ry;
            uz[i] += diagonal * kz + along * rz;
        }
    }
    for (i, row) in out.chunks_exact_mut(3).enumerate() {
        row[0] = ux[i];
        row[1] = uy[i];
        row[2] = uz[i];
    }
}
