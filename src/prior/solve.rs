//! The coefficient solve `(ΓᵀΓ + λI) k = Γᵀu` for K interaction points, in f64.
//!
//! The 3K×3K system is small (K ≈ 20 for two graspers) and symmetric positive definite for λ > 0.
//! Γ is symmetric too (`Γ(r) = Γ(−r)`, each block symmetric), so each block is evaluated once,
//! only the lower triangle of `ΓᵀΓ = ΓΓ` is formed, and faer factorizes it in place: about half
//! the work of a general product and solve. Buffers live in a [`Workspace`], so a request allocates nothing
//! once the workspace has grown to the largest K seen.

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt::factor::{
    LltError, LltParams, LltRegularization, cholesky_in_place, cholesky_in_place_scratch,
};
use faer::linalg::cholesky::llt::solve::solve_in_place_with_conj;
use faer::linalg::matmul::triangular::{BlockStructure, matmul};
use faer::{Accum, Conj, MatMut, MatRef, Par, Spec};

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
    scratch: Scratch,
    pub coefficients: Coefficients,
}

/// faer's scratch space, and the largest request it was made for.
#[derive(Default)]
struct Scratch(Option<(StackReq, MemBuffer)>);

impl std::fmt::Debug for Scratch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_tuple("Scratch")
            .field(&self.0.as_ref().map(|(req, _)| req))
            .finish()
    }
}

impl Scratch {
    /// Room for factorizing an `n × n` system, grown when too small.
    fn stack(&mut self, n: usize) -> &mut MemStack {
        let needed = cholesky_in_place_scratch::<f64>(n, Par::Seq, default_params());
        let fits = self.0.as_ref().is_some_and(|(held, _)| held.or(needed) == *held);
        if !fits {
            self.0 = None;
        }
        let (_, buffer) = self.0.get_or_insert_with(|| (needed, MemBuffer::new(needed)));
        MemStack::new(buffer)
    }
}

fn default_params() -> Spec<LltParams, f64> {
    Spec::default()
}

/// Views `buffer`, resized to `rows × cols` values, as a column-major matrix; old values stay
/// (every caller overwrites what it reads).
fn matrix(buffer: &mut Vec<f64>, rows: usize, cols: usize) -> MatMut<'_, f64> {
    buffer.resize(rows * cols, 0.0);
    MatMut::from_column_major_slice_mut(buffer, rows, cols)
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
        // Block (i, j) = Γ(x_i − x_j) = block (j, i): each is evaluated once and written to both.
        let mut gamma = matrix(&mut ws.gamma, n, n);
        for j in 0..k {
            for i in j..k {
                let r = std::array::from_fn(|c| points.positions[i][c] - points.positions[j][c]);
                for (a, row) in self.response(r).iter().enumerate() {
                    for (b, v) in row.iter().enumerate() {
                        gamma[(3 * i + a, 3 * j + b)] = *v;
                        gamma[(3 * j + b, 3 * i + a)] = *v;
                    }
                }
            }
        }
        let gamma = MatRef::from_column_major_slice(&ws.gamma, n, n);
        let mut normal = matrix(&mut ws.normal, n, n);
        // Lower triangle of ΓΓ + λI (ΓᵀΓ = ΓΓ, Γ symmetric); the upper one is never read.
        matmul(
            normal.as_mut(),
            BlockStructure::TriangularLower,
            Accum::Replace,
            gamma,
            BlockStructure::Rectangular,
            gamma,
            BlockStructure::Rectangular,
            1.0,
            Par::Seq,
        );
        for d in 0..n {
            normal[(d, d)] += self.params.lambda;
        }
        let mut rhs = matrix(&mut ws.rhs, n, 1);
        let u = MatRef::from_column_major_slice(points.displacements.as_flattened(), n, 1);
        faer::linalg::matmul::matmul(rhs.as_mut(), Accum::Replace, gamma, u, 1.0, Par::Seq);
        let stack = ws.scratch.stack(n);
        let mut normal = MatMut::from_column_major_slice_mut(&mut ws.normal, n, n);
        match cholesky_in_place(
            normal.as_mut(),
            LltRegularization::default(),
            Par::Seq,
            stack,
            default_params(),
        ) {
            Ok(_) => {}
            Err(LltError::NonPositivePivot { .. }) => return Err(SolveError::NotPositiveDefinite { points: k }),
        }
        let rhs = MatMut::from_column_major_slice_mut(&mut ws.rhs, n, 1);
        solve_in_place_with_conj(normal.as_ref(), Conj::No, rhs, Par::Seq, MemStack::new(&mut []));
        for j in 0..k {
            let kj = [ws.rhs[3 * j], ws.rhs[3 * j + 1], ws.rhs[3 * j + 2]];
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
