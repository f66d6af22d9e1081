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

use super::dense::{Dense, cholesky_lower, cholesky_solve_lower, gram_lower, times};
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
        assemble(self, &ws.points, gamma);
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
        cholesky_lower(&mut ws.normal, &mut ws.inverse_pivots)
            .map_err(|_| SolveError::NotPositiveDefinite { points: k })?;
        cholesky_solve_lower(&ws.normal, &ws.inverse_pivots, &mut ws.rhs);
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

/// The interaction points by coordinate.
#[derive(Debug, Default)]
struct PointColumns {
    position: [Vec<f64>; 3],
}

impl PointColumns {
    fn load(&mut self, points: &InteractionPoints) {
        for (c, coordinate) in self.position.iter_mut().enumerate() {
            coordinate.clear();
            coordinate.extend(points.positions.iter().map(|p| p[c]));
        }
    }
}

/// Fills `gamma` (component-major, `3K × 3K`) with `Γ(x_i − x_j)`: the column of point `j`,
/// component `b`, holds `s·[(a/r_ε + b/r_ε³) δ_ab + r_a r_b / r_ε³]` at the row of point `i`,
/// component `a` ([`Kelvinlet::response`] entry by entry). Point `j`'s three columns are written in
/// one pass over the points, nine runs at once.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx2+fma", "x86_64+avx2+fma", "aarch64+neon"))]
fn assemble(kelvinlet: &Kelvinlet, p: &PointColumns, gamma: &mut Dense) {
    let [px, py, pz] = &p.position;
    let k = px.len();
    gamma.reset(3 * k);
    let Kelvinlet {
        scale,
        a,
        b,
        epsilon_sq,
        ..
    } = *kelvinlet;
    let (px, py, pz) = (&px[..k], &py[..k], &pz[..k]);
    for j in 0..k {
        let [x_column, y_column, z_column] = gamma.strided_columns_mut(j, k);
        let [xx, yx, zx] = segments(x_column, k);
        let [xy, yy, zy] = segments(y_column, k);
        let [xz, yz, zz] = segments(z_column, k);
        let (xj, yj, zj) = (px[j], py[j], pz[j]);
        for i in 0..k {
            let (rx, ry, rz) = (px[i] - xj, py[i] - yj, pz[i] - zj);
            let inverse = 1.0 / (rx * rx + ry * ry + rz * rz + epsilon_sq).sqrt();
            let inverse_cubed = inverse * inverse * inverse;
            let diagonal = scale * (a * inverse + b * inverse_cubed);
            let along = scale * inverse_cubed;
            let (ax, ay, az) = (along * rx, along * ry, along * rz);
            xx[i] = ax * rx + diagonal;
            yx[i] = ay * rx;
            zx[i] = az * rx;
            xy[i] = ax * ry;
            yy[i] = ay * ry + diagonal;
            zy[i] = az * ry;
            xz[i] = ax * rz;
            yz[i] = ay * rz;
            zz[i] = az * rz + diagonal;
        }
    }
}

/// A component-major column's three runs of `k` rows (x, y, z).
#[inline(always)]
fn segments(column: &mut [f64], k: usize) -> [&mut [f64]; 3] {
    let (x, rest) = column.split_at_mut(k);
    let (y, z) = rest.split_at_mut(k);
    [x, y, &mut z[..k]]
}
