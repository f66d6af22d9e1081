//! The f32 field kernel: `u(x) = Σ_j s·[(a/r_ε + b/r_ε³) k_j + r (r·k_j)/r_ε³]` over many nodes.
//!
//! Nodes are stored as a structure of arrays, padded to whole blocks of [`BLOCK`] nodes. Each block
//! accumulates its field in registers/L1 over all interaction points, then writes interleaved
//! (N, 3) rows. The block function is compiled for several x86-64 feature levels and picked at run
//! time (AVX-512, AVX2+FMA, SSE4.1, baseline), so one portable binary runs at the speed of the CPU it
//! finds. Blocks are spread over cores for large meshes, from rayon's pool (or from outside it
//! when the field is large enough to pay for handing it over).

use multiversion::multiversion;
use multiversion::target::target_cfg;
use rayon::prelude::*;

use super::cloud::{BLOCK, NodeCloud};
use super::{Coefficients, Kelvinlet};

/// Below this many nodes one core is faster than the cost of waking others.
const PARALLEL_MIN_NODES: usize = 4096;

/// From a thread outside rayon's pool (a quick request answered on the connection's thread), the
/// whole field is handed to the pool and waited for: about 80 µs of wake-ups on a small virtual
/// machine, worth paying only for fields several times that long (node–point pairs).
const HANDOVER_MIN_TERMS: usize = 1 << 21;

/// Kernel constants in f32.
#[derive(Clone, Copy)]
struct Constants {
    a: f32,
    b: f32,
    epsilon_sq: f32,
}

impl Kelvinlet {
    /// The field of `coefficients` at every node of `cloud`, written into `out` ((N, 3) rows) on
    /// the CPU, whatever the cloud's residence (the CPU backend, the GPU's reference and fallback).
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
        if splits_over_pool(cloud, coefficients.len()) {
            out.par_chunks_mut(3 * BLOCK).enumerate().with_min_len(8).for_each(run);
        } else {
            out.chunks_mut(3 * BLOCK).enumerate().for_each(run);
        }
    }
}

/// Whether a field of `points` over `cloud` is spread over rayon's pool from this thread.
pub(super) fn splits_over_pool(cloud: &NodeCloud, points: usize) -> bool {
    let in_pool = rayon::current_thread_index().is_some();
    cloud.len() >= PARALLEL_MIN_NODES && (in_pool || cloud.len().saturating_mul(points) >= HANDOVER_MIN_TERMS)
}

/// Nodes evaluated together against every interaction point: one AVX-512 register per coordinate
/// (two AVX2 ones), so positions and sums stay in registers while the points stream past.
const LANES: usize = 16;

/// One block of nodes: `out` holds up to BLOCK interleaved rows (fewer in the last block).
///
/// Products are fused into FMAs where the CPU has them (Rust never contracts `a * b + c` itself),
/// and `1/r_ε` comes from the CPU's reciprocal square root estimate refined by one Newton step:
/// a square root and a division per term would take the divider about twice as long as all the
/// other arithmetic together.
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
    #[target_cfg(any(target_feature = "fma", target_arch = "aarch64"))]
    #[inline(always)]
    fn fused(a: f32, b: f32, c: f32) -> f32 {
        a.mul_add(b, c)
    }
    #[target_cfg(not(any(target_feature = "fma", target_arch = "aarch64")))]
    #[inline(always)]
    fn fused(a: f32, b: f32, c: f32) -> f32 {
        a * b + c
    }
    #[target_cfg(all(target_arch = "x86_64", target_feature = "avx512f"))]
    #[inline(always)]
    fn inverse_sqrt(x: &[f32; LANES]) -> [f32; LANES] {
        // SAFETY: this version of the function runs only where AVX-512F was detected.
        unsafe { x86::inverse_sqrt_avx512(x) }
    }
    #[target_cfg(all(
        target_arch = "x86_64",
        target_feature = "avx2",
        target_feature = "fma",
        not(target_feature = "avx512f")
    ))]
    #[inline(always)]
    fn inverse_sqrt(x: &[f32; LANES]) -> [f32; LANES] {
        // SAFETY: this version of the function runs only where AVX2 and FMA were detected.
        unsafe { x86::inverse_sqrt_avx2(x) }
    }
    #[target_cfg(not(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma")))]
    #[inline(always)]
    fn inverse_sqrt(x: &[f32; LANES]) -> [f32; LANES] {
        x.map(|v| 1.0 / v.sqrt())
    }
    /// Adds the field of interaction point `j` at the lanes' nodes to `u`.
    #[inline(always)]
    fn add_term(node: [&[f32; LANES]; 3], c: &Coefficients, j: usize, k: Constants, u: &mut [[f32; LANES]; 3]) {
        let [x, y, z] = node;
        let (px, py, pz) = (c.x[j], c.y[j], c.z[j]);
        let (kx, ky, kz) = (c.kx[j], c.ky[j], c.kz[j]);
        let r_sq: [f32; LANES] = std::array::from_fn(|i| {
            let (rx, ry, rz) = (x[i] - px, y[i] - py, z[i] - pz);
            fused(rx, rx, fused(ry, ry, fused(rz, rz, k.epsilon_sq)))
        });
        let inv_r = inverse_sqrt(&r_sq);
        for i in 0..LANES {
            let (rx, ry, rz) = (x[i] - px, y[i] - py, z[i] - pz);
            let inv = inv_r[i];
            let inv3 = inv * inv * inv;
            let diagonal = fused(k.b, inv3, k.a * inv);
            let along = fused(rx, kx, fused(ry, ky, rz * kz)) * inv3;
            u[0][i] = fused(diagonal, kx, fused(along, rx, u[0][i]));
            u[1][i] = fused(diagonal, ky, fused(along, ry, u[1][i]));
            u[2][i] = fused(diagonal, kz, fused(along, rz, u[2][i]));
        }
    }
    let mut u = [[0.0f32; BLOCK]; 3];
    let (xs, ys, zs) = (
        xs.as_chunks::<LANES>().0,
        ys.as_chunks::<LANES>().0,
        zs.as_chunks::<LANES>().0,
    );
    for (chunk, lane) in (0..BLOCK).step_by(LANES).enumerate() {
        let node = [&xs[chunk], &ys[chunk], &zs[chunk]];
        // Even and odd points into separate sums: two independent FMA chains keep the FMA units
        // busy where one would wait on its own latency.
        let mut even = [[0.0f32; LANES]; 3];
        let mut odd = [[0.0f32; LANES]; 3];
        let mut j = 0;
        while j + 1 < c.len() {
            add_term(node, c, j, k, &mut even);
            add_term(node, c, j + 1, k, &mut odd);
            j += 2;
        }
        if j < c.len() {
            add_term(node, c, j, k, &mut even);
        }
        for d in 0..3 {
            for i in 0..LANES {
                u[d][lane + i] = even[d][i] + odd[d][i];
            }
        }
    }
    for (i, row) in out.chunks_exact_mut(3).enumerate() {
        row[0] = u[0][i];
        row[1] = u[1][i];
        row[2] = u[2][i];
    }
}

/// `1/√x` on 16 lanes: the hardware estimate (relative error at most 2⁻¹⁴ with AVX-512, 1.5·2⁻¹² with
/// AVX) and one Newton step `y (3 − x y²) / 2`, which squares that error: within 4e-7 of the exact
/// value, a few f32 ulps, for the positive, normal `x = |r|² + ε²` the kernel takes.
#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    use super::LANES;

    #[target_feature(enable = "avx512f")]
    pub fn inverse_sqrt_avx512(x: &[f32; LANES]) -> [f32; LANES] {
        let mut out = [0.0f32; LANES];
        // SAFETY: both pointers address LANES = 16 f32s, one 512-bit vector (unaligned access).
        unsafe {
            let v = _mm512_loadu_ps(x.as_ptr());
            let y = _mm512_rsqrt14_ps(v);
            let half_x_y = _mm512_mul_ps(_mm512_mul_ps(v, _mm512_set1_ps(0.5)), y);
            let step = _mm512_fnmadd_ps(half_x_y, y, _mm512_set1_ps(1.5));
            _mm512_storeu_ps(out.as_mut_ptr(), _mm512_mul_ps(y, step));
        }
        out
    }

    #[target_feature(enable = "avx2,fma")]
    pub fn inverse_sqrt_avx2(x: &[f32; LANES]) -> [f32; LANES] {
        let mut out = [0.0f32; LANES];
        for half in 0..2 {
            // SAFETY: each half is 8 f32s, one 256-bit vector (unaligned access).
            unsafe {
                let v = _mm256_loadu_ps(x.as_ptr().add(8 * half));
                let y = _mm256_rsqrt_ps(v);
                let half_x_y = _mm256_mul_ps(_mm256_mul_ps(v, _mm256_set1_ps(0.5)), y);
                let step = _mm256_fnmadd_ps(half_x_y, y, _mm256_set1_ps(1.5));
                _mm256_storeu_ps(out.as_mut_ptr().add(8 * half), _mm256_mul_ps(y, step));
            }
        }
        out
    }
}
