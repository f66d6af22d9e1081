//! The coefficient solve `(ΓᵀΓ + λI) k = Γᵀu` for K interaction points, in f64.
//!
//! The 3K×3K system is small (K ≈ 20 for two graspers) and symmetric positive definite for λ > 0.
//! Γ is symmetric too (`Γ(r) = Γ(−r)`, each block symmetric), so `ΓᵀΓ = ΓΓ`, of which only the
//! lower triangle is formed, and it is factorized in place by the small dense kernels of
//! [`super::dense`]. Unknowns are ordered by component (all x, then all y, then all z): a column
//! of Γ is then three runs over the points, which vectorize, where point-major order would
//! interleave them. Buffers live in a [`Workspace`], so a request allocates nothing
//! once the workspace has grown to the largest K seen.

use multiversion::multiversion;

use super::dense::{Dense, cholesky_solve, gram_lower, times};
use super::{InteractionPoints, Kelvinlet};

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SolveError {
    #[error("the Kelvinlet system for {points} interaction points is not positive definite")]
    NotPositiveDefinite { points: usize },
}

/// Coefficients ready for the f32 field kernel: point positions and `s · k_j`, structure of arrays.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Coefficients {
    pub x: Vec<f32>,
    pub y: Vec<f32>,
    pub z: Vec<f32>,
    pub kx: Vec<f32>,
    pub ky: Vec<f32>,
    pub kz: Vec<f32>,
}

impl Coefficients {
    pub fn len(&self) -> usize {
        self.x.len()
    }

    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    fn clear(&mut self) {
        for v in [
            &mut self.x,
            &mut self.y,
            &mut self.z,
            &mut self.kx,
            &mut self.ky,
            &mut self.kz,
        ] {
            v.clear();
        }
    }
}

/// Reusable buffers for one request at a time.
#[derive(Debug, Default)]
pub struct Workspace {
    points: PointColumns,
    /// Scratch for [`assemble`]: one point's offsets and scales from every point.
    scratch: Vec<f64>,
    gamma: Dense,
    normal: Dense,
    displacements: Vec<f64>,
    rhs: Vec<f64>,
    inverse_pivots: Vec<f64>,
    pub coefficients: Coefficients,
}

impl Kelvinlet {
    /// Solves for the coefficients of `points` into `ws.coefficients`.
    ///
    /// A single point needs no system: `Γ(0) = I`, so its coefficient is its displacement and the
    /// field reproduces it exactly; λ regularizes only the coupling between several points.
    pub fn solve(&self, points: &InteractionPoints, ws: &mut Workspace) -> Result<(), SolveError> {
        let k = points.len();
        let n = 3 * k;
        ws.coefficients.clear();
        if k == 1 {
            self.push_coefficient(ws, points.positions[0], points.displacements[0]);
            return Ok(());
        }
        let gamma = &mut ws.gamma;
        ws.points.load(points);
        assemble(self, &ws.points, &mut ws.scratch, gamma);
        // Lower triangle of ΓΓ + λI (ΓᵀΓ = ΓΓ, Γ symmetric); the upper one is never read.
        gram_lower(gamma, &mut ws.normal);
        for d in 0..n {
            ws.normal.set(d, d, ws.normal.get(d, d) + self.params.lambda);
        }
        // u by component, like Γ's rows.
        ws.displacements.clear();
        for c in 0..3 {
            ws.displacements.extend(points.displacements.iter().map(|u| u[c]));
        }
        ws.rhs.resize(n, 0.0);
        times(gamma, &ws.displacements, &mut ws.rhs);
        cholesky_solve(&mut ws.normal, &mut ws.rhs, &mut ws.inverse_pivots)
            .map_err(|_| SolveError::NotPositiveDefinite { points: k })?;
        for j in 0..k {
            let kj = [ws.rhs[j], ws.rhs[k + j], ws.rhs[2 * k + j]];
            self.push_coefficient(ws, points.positions[j], kj);
        }
        Ok(())
    }

    fn push_coefficient(&self, ws: &mut Workspace, position: [f64; 3], k: [f64; 3]) {
        let c = &mut ws.coefficients;
        c.x.push(position[0] as f32);
        c.y.push(position[1] as f32);
        c.z.push(position[2] as f32);
        c.kx.push((self.scale * k[0]) as f32);
        c.ky.push((self.scale * k[1]) as f32);
        c.kz.push((self.scale * k[2]) as f32);
    }
}

/// Lanes of the assembly's chunks: one AVX-512 register of f64.
const LANES: usize = 8;

/// The interaction points by coordinate, each padded with zeros to whole chunks of [`LANES`].
#[derive(Debug, Default)]
struct PointColumns {
    len: usize,
    position: [Vec<f64>; 3],
}

impl PointColumns {
    fn load(&mut self, points: &InteractionPoints) {
        self.len = points.len();
        let padded = self.len.next_multiple_of(LANES);
        for (c, coordinate) in self.position.iter_mut().enumerate() {
            coordinate.clear();
            coordinate.extend(points.positions.iter().map(|p| p[c]));
            coordinate.resize(padded, 0.0);
        }
    }
}

/// Fills `gamma` (component-major, `3K × 3K`) with `Γ(x_i − x_j)`: the column of point `j`,
/// component `b`, holds `s·[(a/r_ε + b/r_ε³) δ_ab + r_a r_b / r_ε³]` at the row of point `i`,
/// component `a` ([`Kelvinlet::response`] entry by entry). For each point `j`, the square roots and
/// divisions run first, over whole chunks of points into `scratch` (the padding points' values are
/// finite, since ε > 0, and unused): a loop that vectorizes without a scalar tail, where the
/// expensive operations sat in the tail of one loop over `K` points. The nine runs of the columns
/// are then two multiplications per entry.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx2+fma", "x86_64+avx2+fma", "aarch64+neon"))]
fn assemble(kelvinlet: &Kelvinlet, p: &PointColumns, scratch: &mut Vec<f64>, gamma: &mut Dense) {
    let k = p.len;
    let padded = p.position[0].len();
    gamma.reset(3 * k);
    scratch.resize(5 * padded, 0.0);
    let Kelvinlet {
        scale,
        a,
        b,
        epsilon_sq,
        ..
    } = *kelvinlet;
    let [px, py, pz] = p.position.each_ref().map(|c| c.as_chunks::<LANES>().0);
    for j in 0..k {
        let (xj, yj, zj) = (p.position[0][j], p.position[1][j], p.position[2][j]);
        let (chunks, _) = scratch.as_chunks_mut::<LANES>();
        let (r, rest) = chunks.split_at_mut(3 * padded / LANES);
        let (along, diagonal) = rest.split_at_mut(padded / LANES);
        let (rx, rest) = r.split_at_mut(padded / LANES);
        let (ry, rz) = rest.split_at_mut(padded / LANES);
        for c in 0..padded / LANES {
            rx[c] = std::array::from_fn(|l| px[c][l] - xj);
            ry[c] = std::array::from_fn(|l| py[c][l] - yj);
            rz[c] = std::array::from_fn(|l| pz[c][l] - zj);
            let inverse: [f64; LANES] = std::array::from_fn(|l| {
                1.0 / (rx[c][l] * rx[c][l] + ry[c][l] * ry[c][l] + rz[c][l] * rz[c][l] + epsilon_sq).sqrt()
            });
            along[c] = std::array::from_fn(|l| scale * inverse[l] * inverse[l] * inverse[l]);
            diagonal[c] = std::array::from_fn(|l| scale * a * inverse[l] + b * along[c][l]);
        }
        let run = |i: usize| &scratch[i * padded..i * padded + k];
        let (r, along, diagonal) = ([run(0), run(1), run(2)], run(3), run(4));
        for (col, column) in gamma.strided_columns_mut(j, k).into_iter().enumerate() {
            for (row, segment) in column.chunks_exact_mut(k).enumerate() {
                let entries = segment.iter_mut().zip(along).zip(r[row].iter().zip(r[col]));
                if row == col {
                    for (((entry, along), (x, _)), d) in entries.zip(diagonal) {
                        *entry = along * x * x + d;
                    }
                } else {
                    for ((entry, along), (x, y)) in entries {
                        *entry = along * x * y;
                    }
                }
            }
        }
    }
}
