//! Linear solves with the constrained Newton tangent: a sparse Cholesky factor whose storage lives
//! as long as the solve, and conjugate gradients preconditioned by the factor of an earlier
//! tangent, so that most Newton iterations need no factorization at all.
//!
//! Within one grasp the tangent changes slowly enough that an old factor brings a new system to the
//! solver's accuracy in a handful of iterations. A factor that only preconditions is kept in f32:
//! CG runs against the f64 tangent, so the answer is as exact, while the factorization and the
//! (memory-bound) triangular solves move half the bytes.

use std::sync::Arc;

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::sparse::SparseColMatRef;
use faer::sparse::linalg::LltError;
use faer::sparse::linalg::cholesky::{LltRef, SymbolicCholesky};
use faer::sparse::linalg::matmul::sparse_dense_matmul;
use faer::{Accum, Conj, MatMut, MatRef, Par, Side};

use super::supernodal::SupernodalLayout;

/// The precision a factor is stored in.
pub trait Precision: faer::traits::ComplexField + Copy + Default + 'static {
    fn narrow(value: f64) -> Self;
    fn widen(self) -> f64;
    /// x ← (L Lᵀ)⁻¹ x by [`SupernodalLayout`]'s sweeps, if they exist for this precision (f32, the
    /// precision of the preconditioner every CG iteration applies); `false` leaves it to faer.
    fn solve_supernodal(layout: &SupernodalLayout, values: &[Self], x: &mut [Self], scratch: &mut Vec<Self>) -> bool;
}

impl Precision for f64 {
    fn narrow(value: f64) -> Self {
        value
    }
    fn widen(self) -> f64 {
        self
    }
    fn solve_supernodal(_: &SupernodalLayout, _: &[Self], _: &mut [Self], _: &mut Vec<Self>) -> bool {
        false
    }
}

impl Precision for f32 {
    fn narrow(value: f64) -> Self {
        value as f32
    }
    fn widen(self) -> f64 {
        f64::from(self)
    }
    fn solve_supernodal(layout: &SupernodalLayout, values: &[Self], x: &mut [Self], scratch: &mut Vec<Self>) -> bool {
        layout.solve_in_place(values, x, scratch);
        true
    }
}

/// A Cholesky factor of one tangent, refreshed in place, stored in precision `T`.
pub struct TangentFactor<T: Precision> {
    symbolic: Arc<SymbolicCholesky<usize>>,
    /// The factorized matrix's values in `T`.
    matrix: Vec<T>,
    /// L's values; empty until the first factorization.
    values: Vec<T>,
    /// A right-hand side in `T`.
    vector: Vec<T>,
    scratch: MemBuffer,
    /// Where the factor's supernodes lie, for solves that do not go through faer.
    layout: Option<SupernodalLayout>,
    /// The sweeps' scratch vector.
    sweep: Vec<T>,
    /// Whether `values` holds a complete factor.
    valid: bool,
}

/// What the Newton solver asks of a factor, whatever its precision.
pub trait Factor {
    /// Whether a factor is at hand (from this matrix or an earlier one of the same pattern).
    fn is_valid(&self) -> bool;
    /// Factorizes the lower triangle of `matrix`; on failure the factor is invalid.
    fn factorize(&mut self, matrix: SparseColMatRef<'_, usize, f64>) -> Result<(), LltError>;
    /// x ← A⁻¹ x with the factored A.
    fn solve_in_place(&mut self, x: &mut [f64]);
}

/// Solves `matrix · x = rhs` to ‖rhs − matrix·x‖ ≤ `tolerance`·‖rhs‖ by conjugate gradients
/// preconditioned with `precondition` (z ← M⁻¹ z, M symmetric positive definite: the factor of an
/// earlier tangent, alone or with a block solved exactly), starting from x = 0. `matrix` must hold
/// both triangles; it need not be positive definite (see [`Krylov`]).
pub fn conjugate_gradients(
    matrix: SparseColMatRef<'_, usize, f64>,
    rhs: &[f64],
    x: &mut [f64],
    tolerance: f64,
    max_iterations: usize,
    precondition: &mut dyn FnMut(&mut [f64]),
) -> Krylov {
    let n = rhs.len();
    x.fill(0.0);
    let goal = tolerance * norm(rhs);
    let mut r = rhs.to_vec();
    if norm(&r) <= goal {
        return Krylov::Converged(0);
    }
    let mut z = r.clone();
    precondition(&mut z);
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    let mut ap = vec![0.0; n];
    for iteration in 1..=max_iterations {
        sparse_dense_matmul(
            MatMut::from_column_major_slice_mut(&mut ap, n, 1),
            Accum::Replace,
            matrix,
            MatRef::from_column_major_slice(&p, n, 1),
            1.0,
            Par::Seq,
        );
        let curvature = dot(&p, &ap);
        if curvature <= 0.0 || !curvature.is_finite() {
            if iteration == 1 {
                x.copy_from_slice(&z);
            }
            return Krylov::NegativeCurvature(iteration - 1);
        }
        let alpha = rz / curvature;
        for i in 0..n {
            x[i] += alpha * p[i];
            r[i] -= alpha * ap[i];
        }
        if norm(&r) <= goal {
            return Krylov::Converged(iteration);
        }
        z.copy_from_slice(&r);
        precondition(&mut z);
        let next = dot(&r, &z);
        let beta = next / rz;
        rz = next;
        for i in 0..n {
            p[i] = z[i] + beta * p[i];
        }
    }
    Krylov::Stalled
}

/// How a preconditioned conjugate-gradient solve ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Krylov {
    /// Reached the tolerance in this many iterations.
    Converged(usize),
    /// Ran out of iterations: the factor no longer describes the matrix well enough.
    Stalled,
    /// pᵀAp ≤ 0 after this many iterations: the matrix is not positive definite. The solution
    /// holds the last iterate, or the preconditioned right-hand side if there was none: a
    /// direction along which xᵀ·rhs > 0 (truncated CG, as in Steihaug's trust-region Newton).
    NegativeCurvature(usize),
}

impl<T: Precision> TangentFactor<T> {
    pub fn new(symbolic: Arc<SymbolicCholesky<usize>>) -> Self {
        let par = Par::Seq;
        let scratch = MemBuffer::new(StackReq::any_of(&[
            symbolic.factorize_numeric_llt_scratch::<T>(par, Default::default()),
            symbolic.solve_in_place_scratch::<T>(1, par),
        ]));
        Self {
            layout: SupernodalLayout::new(&symbolic),
            sweep: Vec::new(),
            symbolic,
            matrix: Vec::new(),
            values: Vec::new(),
            vector: Vec::new(),
            scratch,
            valid: false,
        }
    }
}

impl<T: Precision> Factor for TangentFactor<T> {
    fn is_valid(&self) -> bool {
        self.valid
    }

    fn factorize(&mut self, matrix: SparseColMatRef<'_, usize, f64>) -> Result<(), LltError> {
        self.valid = false;
        self.matrix.clear();
        self.matrix.extend(matrix.val().iter().map(|&v| T::narrow(v)));
        self.values.resize(self.symbolic.len_val(), T::default());
        self.symbolic.factorize_numeric_llt(
            &mut self.values,
            SparseColMatRef::new(matrix.symbolic(), &self.matrix),
            Side::Lower,
            Default::default(),
            Par::Seq,
            MemStack::new(&mut self.scratch),
            Default::default(),
        )?;
        self.valid = true;
        Ok(())
    }

    fn solve_in_place(&mut self, x: &mut [f64]) {
        self.solve_narrowed(x, false);
    }
}

impl<T: Precision> TangentFactor<T> {
    /// x ← A⁻¹ x by faer's own supernodal solve: the reference the sweeps of [`SupernodalLayout`] are
    /// tested and benchmarked against.
    pub fn solve_with_faer(&mut self, x: &mut [f64]) {
        self.solve_narrowed(x, true);
    }

    fn solve_narrowed(&mut self, x: &mut [f64], with_faer: bool) {
        debug_assert!(self.valid, "solve with no factor");
        let n = x.len();
        self.vector.clear();
        self.vector.extend(x.iter().map(|&v| T::narrow(v)));
        let swept = !with_faer
            && self
                .layout
                .as_ref()
                .is_some_and(|layout| T::solve_supernodal(layout, &self.values, &mut self.vector, &mut self.sweep));
        if !swept {
            LltRef::new(&self.symbolic, &self.values).solve_in_place_with_conj(
                Conj::No,
                MatMut::from_column_major_slice_mut(&mut self.vector, n, 1),
                Par::Seq,
                MemStack::new(&mut self.scratch),
            );
        }
        for (x, v) in x.iter_mut().zip(&self.vector) {
            *x = v.widen();
        }
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn norm(a: &[f64]) -> f64 {
    dot(a, a).sqrt()
}
