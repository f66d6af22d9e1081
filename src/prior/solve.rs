//! The coefficient solve `(ΓᵀΓ + λI) k = Γᵀu` for K interaction points, in f64.
//!
//! The 3K×3K system is small (K ≈ 20 for two graspers) and symmetric positive definite for λ > 0;
//! nalgebra's Cholesky factorizes it in place in buffers kept in a [`Workspace`], so a request
//! allocates nothing once the workspace has grown to the largest K seen.

use nalgebra::{DMatrix, DVector, DVectorView, Dyn, VecStorage};

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
    gamma: Vec<f64>,
    normal: Vec<f64>,
    rhs: Vec<f64>,
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
        // Γ (column-major, as nalgebra stores it): block (i, j) = Γ(x_i − x_j).
        ws.gamma.clear();
        ws.gamma.resize(n * n, 0.0);
        for j in 0..k {
            for i in 0..k {
                let r = std::array::from_fn(|c| points.positions[i][c] - points.positions[j][c]);
                let block = self.response(r);
                for (a, row) in block.iter().enumerate() {
                    for (b, v) in row.iter().enumerate() {
                        ws.gamma[(3 * j + b) * n + 3 * i + a] = *v;
                    }
                }
            }
        }
        let gamma = DMatrix::from_vec_storage(VecStorage::new(Dyn(n), Dyn(n), std::mem::take(&mut ws.gamma)));
        let u = DVectorView::from_slice(points.displacements.as_flattened(), n);
        ws.normal.clear();
        ws.normal.resize(n * n, 0.0);
        let mut normal = DMatrix::from_vec_storage(VecStorage::new(Dyn(n), Dyn(n), std::mem::take(&mut ws.normal)));
        // Γ is symmetric (Γ(r) = Γ(−r) and each block is symmetric), so ΓᵀΓ = ΓΓ, which nalgebra
        // computes with a blocked SIMD GEMM; its transposed product does not.
        gamma.mul_to(&gamma, &mut normal);
        for d in 0..n {
            normal[(d, d)] += self.params.lambda;
        }
        ws.rhs.clear();
        ws.rhs.resize(n, 0.0);
        let mut rhs = DVector::from_vec_storage(VecStorage::new(Dyn(n), nalgebra::U1, std::mem::take(&mut ws.rhs)));
        gamma.tr_mul_to(&u, &mut rhs);
        ws.gamma = gamma.data.into();
        let Some(cholesky) = normal.cholesky() else {
            ws.rhs = rhs.data.into();
            return Err(SolveError::NotPositiveDefinite { points: k });
        };
        cholesky.solve_mut(&mut rhs);
        ws.normal = cholesky.unpack().data.into();
        for j in 0..k {
            let kj = [rhs[3 * j], rhs[3 * j + 1], rhs[3 * j + 2]];
            self.push_coefficient(ws, points.positions[j], kj);
        }
        ws.rhs = rhs.data.into();
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
