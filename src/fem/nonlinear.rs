//! Total-Lagrangian P1 finite elements with compressible Mooney–Rivlin (docs/design.md §4), solved by
//! Newton–Raphson with the consistent tangent, a backtracking line search on the potential energy and
//! adaptive load stepping.
//!
//! The unknowns are every DOF of every node that is not `fixed`; prescribed (grasped) DOFs stay in the
//! system as identity rows. The sparsity pattern is therefore the same for every grasp, and the
//! symbolic Cholesky factorization is computed once per mesh. Within a solve the prescribed set does
//! not change, so the factor of one tangent preconditions the next ones (see [`super::factor`]).
//!
//! A grasp's large local deformation is solved apart: the nodes around the held ones are relaxed
//! alone after every global step ([`Elimination`], module `elimination`), and a load step that ends
//! on another equilibrium branch than the quasi-static path's is undone ([`Hyperelastic::on_path`]).

use std::sync::Arc;
use std::time::{Duration, Instant};

use faer::Side;
use faer::perm::PermRef;
use faer::sparse::linalg::cholesky::{SymbolicCholesky, SymmetricOrdering, factorize_symbolic_cholesky};
use faer::sparse::{SparseColMat, SparseColMatRef, SymbolicSparseColMat, Triplet};
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use super::FemError;
use super::factor::{Factor, Krylov, Precision, TangentFactor, conjugate_gradients};
use super::hyperelastic::{MooneyRivlin, TangentTerms};
use super::linear::{DofMap, shape_gradients};
use super::ordering::nested_dissection;
use crate::mesh::TetMesh;
use crate::mesh::topology::Vec3;

mod elimination;

use elimination::{Patch, PatchBlock};

/// How hard the solver tries; the defaults suit the phantom's grasps.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NewtonOptions {
    /// Converged when ‖residual‖ ≤ this × the larger of ‖external force‖ and ‖reactions‖ ...
    pub residual_tolerance: f64,
    /// ... and the energy increment |Δu·r| ≤ this × the load step's first one.
    pub energy_tolerance: f64,
    /// Load steps before the last only lead the way to it: they end at ‖residual‖ ≤ this × the
    /// same scale, and the last meets both criteria above. (Hyperelastic equilibrium does not
    /// depend on the path, only on where it ends.)
    pub intermediate_tolerance: f64,
    /// Newton iterations per load step before the step is cut.
    pub max_iterations: usize,
    /// The first load step, as a fraction of the whole load.
    pub initial_step: f64,
    /// Load-step halvings before the solve is declared failed.
    pub max_step_cuts: usize,
    /// No load step is longer than this fraction of the load. 1 lets easy steps grow; 0.02 follows
    /// the quasi-static path closely enough to be the reference for which of several equilibria a
    /// grasp reaches (see [`Hyperelastic::on_path`]).
    pub max_load_step: f64,
    /// Solve Newton corrections by conjugate gradients preconditioned with the factor of an earlier
    /// tangent of the same solve, factorizing only when that does not converge. Off: every
    /// correction factorizes its own tangent (the reference the fast path is tested against).
    pub reuse_factorization: bool,
    /// Grasps only: solve the nodes around the held ones alone after every global step (see
    /// [`Elimination`]); `None` solves every node only globally.
    pub elimination: Option<Elimination>,
}

/// How a grasp's neighbourhood is eliminated: the nodes within `rings` element rings of the held
/// nodes are solved exactly, alone, after every predictor and every global Newton step, so that the
/// global iteration only sees the smooth rest of the organ (module `elimination`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Elimination {
    pub rings: usize,
    /// The first load step, as a fraction of the grasp. The rings take the large local deformation
    /// at once, but the rest of the organ still turns through large rotations: a fifth of the grasp
    /// per step keeps its tangent close enough to the last that Newton needs two or three
    /// corrections a step.
    pub initial_step: f64,
}

impl Default for Elimination {
    fn default() -> Self {
        Self {
            rings: 2,
            initial_step: 0.2,
        }
    }
}

/// Relative residual to which conjugate gradients solve a Newton correction near the solution (an
/// inexact Newton method): each correction then cuts the nonlinear residual about a hundredfold,
/// as fast as exact corrections do from the residuals Newton starts them at.
const KRYLOV_TOLERANCE: f64 = 1e-2;
/// The loosest tolerance a correction far from the solution is solved to (see [`Forcing`]).
const KRYLOV_TOLERANCE_FAR: f64 = 0.3;
/// Steps stop this fraction of the way to where the first element would collapse (J = 0): the
/// barrier in the energy keeps accepted states away from it, and a step that ends at the root
/// would leave an element with no volume.
const FEASIBLE_FRACTION: f64 = 0.9;
/// The feasibility search looks this far along a direction; no step is longer than 1.
const FEASIBLE_HORIZON: f64 = 2.0;
/// A predictor shorter than this fraction of its load step means an element is collapsing
/// already: the step is cut instead of crawling.
const MIN_PREDICTOR_FRACTION: f64 = 1e-4;
/// A load step whose potential energy rose by more than this fraction less than the least work the
/// graspers can have done on the way ended on another equilibrium branch (see
/// [`Hyperelastic::on_path`]): a snap the quasi-static path does not take. It is undone and
/// halved.
const PATH_TOLERANCE: f64 = 0.02;
/// On a load step where the graspers' rate of work fell, the energy gained may fall short of the
/// trapezoid of the two rates by at most this fraction. Along a smooth branch it is the trapezoid to
/// second order (softening steps of seeds 3 and 7 gain it within 0.1–0.6 %); a snap drops the rate
/// and releases energy, and falls further short (sample 7 of seed 3, from 50 % to 80 % of the grasp,
/// 1.9 %), while the least rate alone misses it (the snap ends where the rate is lowest).
const SOFTENING_TOLERANCE: f64 = 0.01;
/// A load step this short that still jumps has met a limit point of its branch: the tissue snaps
/// there whatever the step, and the jump is kept.
const SNAP_STEP: f64 = 0.02;
/// Shifted factorizations of one indefinite tangent before the load step is cut.
const MAX_SHIFTS: usize = 8;
/// Conjugate-gradient iterations before an old factor is given up for a new one.
const MAX_KRYLOV_ITERATIONS: usize = 12;
/// A correction that needed more conjugate-gradient iterations than this asks for a fresh factor
/// at the next one: on the phantom a factorization costs about eight iterations.
const REFACTOR_AFTER: usize = 8;

impl Default for NewtonOptions {
    fn default() -> Self {
        Self {
            residual_tolerance: 1e-6,
            energy_tolerance: 1e-12,
            intermediate_tolerance: 1e-3,
            max_iterations: 25,
            initial_step: 1.0,
            max_step_cuts: 12,
            max_load_step: 1.0,
            reuse_factorization: true,
            elimination: Some(Elimination::default()),
        }
    }
}

/// One Newton iteration, for reports and tests.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Iteration {
    pub load_step: usize,
    /// Load fraction this step is heading for.
    pub load: f64,
    /// ‖free residual‖ before the update (N).
    pub residual: f64,
    /// Total potential energy before the update (J).
    pub energy: f64,
    /// Line-search step length taken (1 = full Newton step).
    pub step_length: f64,
}

/// What a solve took.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct SolveStats {
    pub load_steps: usize,
    pub step_cuts: usize,
    pub newton_iterations: usize,
    /// Trial states rejected because an element inverted (J ≤ 0).
    pub inverted_trials: usize,
    /// Predictors shortened to keep every element clear of inversion (the load step ends where the
    /// shortened predictor lands; not a failure).
    #[serde(default)]
    pub shortened_predictors: usize,
    /// Tangents that were not positive definite and were factorized with a diagonal shift.
    pub shifted_factorizations: usize,
    /// Numeric Cholesky factorizations of the tangent (a shifted retry counts again).
    #[serde(default)]
    pub factorizations: usize,
    /// Conjugate-gradient iterations preconditioned by an earlier factor.
    #[serde(default)]
    pub krylov_iterations: usize,
    /// Newton iterations on the eliminated neighbourhood of the graspers (each a dense solve of a
    /// few hundred unknowns).
    #[serde(default)]
    pub local_iterations: usize,
    /// Load steps undone because they ended on another equilibrium branch than the one they started
    /// on (see [`PATH_TOLERANCE`]).
    #[serde(default)]
    pub branch_jumps: usize,
}

/// Where a solve's time went. Kept apart from [`SolveStats`], which datasets store: timings differ
/// from run to run, counts do not.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SolveProfile {
    /// Element loops computing forces and tangents.
    pub assembly: Duration,
    /// Numeric Cholesky factorizations.
    pub factorization: Duration,
    /// Triangular solves and conjugate gradients.
    pub linear_solve: Duration,
    /// Energy evaluations of line searches and predictor checks.
    pub line_search: Duration,
    /// Solving the graspers' eliminated neighbourhood.
    pub elimination: Duration,
}

impl SolveProfile {
    pub fn add(&mut self, other: &SolveProfile) {
        self.assembly += other.assembly;
        self.factorization += other.factorization;
        self.linear_solve += other.linear_solve;
        self.line_search += other.line_search;
        self.elimination += other.elimination;
    }
}

/// A converged equilibrium: displacement of every node from the reference configuration.
#[derive(Debug, Clone)]
pub struct Equilibrium {
    pub displacement: Vec<[f64; 3]>,
    /// The converged states of the load steps before the last, in order: each the equilibrium of
    /// its fraction of the load, to the intermediate tolerance. The load moves along a straight line,
    /// so each is what a solve of its fraction alone reaches: a sample of its own for no more
    /// solving (`nak datagen` keeps them beside a chunk).
    pub path: Vec<PathState>,
    /// Force the constraints exert on each prescribed node, in the order given.
    pub reactions: Vec<[f64; 3]>,
    pub stats: SolveStats,
    pub profile: SolveProfile,
    pub iterations: Vec<Iteration>,
    pub seconds: f64,
}

/// A converged state on the way to the whole load.
#[derive(Debug, Clone, PartialEq)]
pub struct PathState {
    /// The fraction of the load reached (0 < load < 1).
    pub load: f64,
    pub displacement: Vec<[f64; 3]>,
}

/// The load path: the body force scales from `body_from` to `body_to` while prescribed nodes move
/// linearly from where `start` has them to their targets.
#[derive(Debug, Clone, Copy)]
pub struct Load<'a> {
    pub start: &'a [[f64; 3]],
    /// Absolute displacements (from the reference configuration).
    pub prescribed: &'a [(u32, [f64; 3])],
    pub body_from: f64,
    pub body_to: f64,
}

/// What one solve carries from Newton iteration to iteration.
struct Work {
    stats: SolveStats,
    profile: SolveProfile,
    trace: Vec<Iteration>,
    /// f32 where the factor preconditions CG, f64 where it solves exactly.
    factor: Box<dyn Factor>,
    /// The tangent's CSC values, reassembled each iteration.
    tangent: Vec<f64>,
    /// The factor has grown stale: factorize at the next correction.
    refactor: bool,
    /// The diagonal shift the last indefinite tangent needed.
    last_shift: f64,
    /// The graspers' neighbourhood, when it is eliminated.
    patch: Option<Patch>,
}

/// The tolerance of each Newton correction's linear solve, after Eisenstat and Walker (1996, choice
/// 2): η = 0.9 (‖r_k‖ / ‖r_{k−1}‖)², between [`KRYLOV_TOLERANCE`] and [`KRYLOV_TOLERANCE_FAR`] (their
/// safeguard against η falling too fast only acts above 1/3, so it has nothing to do here). Far from
/// the solution the tangent is only a rough guide, and solving it to 1e-2 bought corrections no
/// better than 0.3 does (on the phantom: a third fewer CG iterations, half the factorizations,
/// slightly fewer Newton iterations); near it the residual falls fast and η is 1e-2 again.
#[derive(Debug, Default)]
struct Forcing {
    previous_residual: Option<f64>,
}

impl Forcing {
    /// The tolerance for the correction at residual norm `residual`.
    fn next(&mut self, residual: f64) -> f64 {
        let eta = match self.previous_residual.replace(residual) {
            None => KRYLOV_TOLERANCE_FAR,
            Some(previous) => 0.9 * (residual / previous).powi(2),
        };
        if eta.is_finite() {
            eta.clamp(KRYLOV_TOLERANCE, KRYLOV_TOLERANCE_FAR)
        } else {
            KRYLOV_TOLERANCE
        }
    }
}

/// Runs `f` and adds its wall time to `slot`.
fn timed<T>(slot: &mut Duration, f: impl FnOnce() -> T) -> T {
    let started = Instant::now();
    let value = f();
    *slot += started.elapsed();
    value
}

/// Why a load step failed; the solver cuts the step and retries until it runs out of cuts.
enum StepFailure {
    Inverted,
    LineSearch,
    NotConverged,
    Factorization(String),
    BranchJump,
    Eliminated,
}

impl StepFailure {
    fn describe(&self) -> String {
        match self {
            Self::Inverted => "an element inverted (J ≤ 0)".into(),
            Self::LineSearch => "the line search found no energy decrease".into(),
            Self::NotConverged => "Newton did not converge in the allowed iterations".into(),
            Self::Factorization(e) => format!("the tangent could not be factorized ({e})"),
            Self::BranchJump => "the load step ended on another equilibrium branch".into(),
            Self::Eliminated => "the graspers' neighbourhood could not be solved".into(),
        }
    }
}

/// The potential energy at a converged state of a load path and the rate dΠ/dλ = R·D at which the
/// graspers do work there (R the reactions, D the held nodes' whole path).
#[derive(Debug, Clone, Copy)]
struct PathPoint {
    energy: f64,
    rate: f64,
}

/// Where a converged load step began and ended.
struct StepEnd {
    load: f64,
    newton: usize,
    start: PathPoint,
    end: PathPoint,
}

/// The tangent on the unknowns and the internal force of every node.
pub type Linearized = (SparseColMat<usize, f64>, Vec<[f64; 3]>);

/// A mesh prepared for hyperelastic solves: geometry, materials, sparsity and symbolic factorization.
pub struct Hyperelastic {
    nodes: usize,
    tets: Vec<[u32; 4]>,
    gradients: Vec<[Vec3; 4]>,
    volumes: Vec<f64>,
    laws: Vec<MooneyRivlin>,
    tet_law: Vec<u16>,
    dofs: DofMap,
    /// Node and component of each unknown.
    dof_owner: Vec<(u32, u8)>,
    pattern: SymbolicSparseColMat<usize>,
    /// For each tetrahedron's 12×12 entry (row-major), its index in the CSC values, or `u32::MAX`
    /// where either DOF is fixed.
    scatter: Vec<[u32; 144]>,
    symbolic: Arc<SymbolicCholesky<usize>>,
    /// Position of each unknown's diagonal entry in the CSC values.
    diagonal: Vec<usize>,
    /// Lumped gravity per node (N).
    body_force: Vec<[f64; 3]>,
    /// Round-off in a sum of element energies (J): energy changes below it carry no information.
    energy_noise: f64,
    options: NewtonOptions,
}

/// Where entry (row, col) lies in the CSC values, if the pattern has it.
fn find(pattern: &SymbolicSparseColMat<usize>, row: usize, col: usize) -> Option<usize> {
    let range = pattern.col_ptr()[col]..pattern.col_ptr()[col + 1];
    let rows = &pattern.row_idx()[range.clone()];
    rows.binary_search(&row).ok().map(|i| range.start + i)
}

impl Hyperelastic {
    /// Prepares `mesh` with its `fixed` nodes held and the body force of model.toml; `gravity`
    /// false drops the body force (verification against load-free solutions).
    pub fn new(mesh: &TetMesh, gravity: bool, options: NewtonOptions) -> Result<Self, FemError> {
        let laws: Vec<MooneyRivlin> = super::region_materials(mesh)?
            .into_iter()
            .map(|m| MooneyRivlin::from_material(m, mesh.config.volumetric_law))
            .collect();
        let fixed = mesh.node_sets.get("fixed").cloned().unwrap_or_default();
        let mut free = vec![true; mesh.node_count()];
        for &n in &fixed {
            free[n as usize] = false;
        }
        // Unknowns numbered in the factor's elimination order, and elements visited by their first
        // node in it: neighbouring elements then write neighbouring tangent entries (the scatter
        // was bound by cache misses in the mesh's own numbering), and the factor needs no
        // permutation.
        let node_order = nested_dissection(&mesh.tets, mesh.node_count(), |n| free[n as usize])?;
        let dofs = DofMap::in_order(mesh.node_count(), &node_order);
        let first_unknown = |t: usize| mesh.tets[t].iter().filter_map(|&n| dofs.get(n, 0)).min();
        let mut element_order: Vec<usize> = (0..mesh.tets.len()).collect();
        element_order.sort_by_key(|&t| first_unknown(t));
        let tets: Vec<[u32; 4]> = element_order.iter().map(|&t| mesh.tets[t]).collect();
        let tet_law: Vec<u16> = element_order.iter().map(|&t| mesh.tet_region[t]).collect();
        let dof_owner: Vec<(u32, u8)> = node_order.iter().flat_map(|&n| (0..3).map(move |c| (n, c))).collect();
        let body = &mesh.config.body;
        let mut body_force = vec![[0.0; 3]; mesh.node_count()];
        let mut gradients = Vec::with_capacity(mesh.tets.len());
        let mut volumes = Vec::with_capacity(mesh.tets.len());
        let mut triplets = Vec::with_capacity(mesh.tets.len() * 144);
        for (tet, &t) in tets.iter().zip(&element_order) {
            let (g, v) = shape_gradients(tet.map(|n| mesh.positions[n as usize])).ok_or(FemError::Degenerate(t))?;
            gradients.push(g);
            volumes.push(v);
            if gravity {
                for &n in tet {
                    for (f, g) in body_force[n as usize].iter_mut().zip(body.gravity) {
                        *f += body.density * g * v / 4.0;
                    }
                }
            }
            for (a, b, i, j) in element_entries() {
                if let (Some(r), Some(c)) = (dofs.get(tet[a], i), dofs.get(tet[b], j)) {
                    triplets.push(Triplet::new(r, c, 0.0));
                }
            }
        }
        let n = dofs.len();
        let matrix = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &triplets)
            .map_err(|e| FemError::Assembly(format!("{e:?}")))?;
        drop(triplets);
        let pattern = matrix
            .symbolic()
            .to_owned()
            .map_err(|e| FemError::Assembly(format!("{e:?}")))?;
        let scatter = tets
            .iter()
            .map(|tet| {
                let mut s = [u32::MAX; 144];
                for (e, (a, b, i, j)) in element_entries().enumerate() {
                    if let (Some(r), Some(c)) = (dofs.get(tet[a], i), dofs.get(tet[b], j)) {
                        s[e] = find(&pattern, r, c).map_or(u32::MAX, |p| p as u32);
                    }
                }
                s
            })
            .collect();
        // The unknowns are already in elimination order. Not `SymmetricOrdering::Identity`: with it
        // faer 0.24 reads the pattern as an upper triangle whatever `side` says, and this one is full.
        let identity: Vec<usize> = (0..n).collect();
        let symbolic = factorize_symbolic_cholesky(
            pattern.as_ref(),
            Side::Lower,
            SymmetricOrdering::Custom(PermRef::new_checked(&identity, &identity, n)),
            Default::default(),
        )
        .map_err(|e| FemError::Assembly(format!("symbolic factorization: {e:?}")))?;
        tracing::debug!(
            unknowns = n,
            tangent_entries = pattern.row_idx().len(),
            factor_entries = symbolic.len_val(),
            "tangent pattern and its Cholesky factor"
        );
        // Every element couples each of its DOFs with itself, so every diagonal entry exists.
        let diagonal = (0..n).map(|d| find(&pattern, d, d).unwrap_or(usize::MAX)).collect();
        // Each element energy is a sum of terms of size ~V(3 C10 + 3 C01 + κ), each exact to ~1e-16.
        let energy_noise = 1e-13
            * tet_law
                .iter()
                .zip(&volumes)
                .map(|(&r, v)| {
                    let law = &laws[r as usize];
                    v * (3.0 * (law.c10 + law.c01) + law.kappa)
                })
                .sum::<f64>();
        Ok(Self {
            energy_noise,
            nodes: mesh.node_count(),
            tets,
            gradients,
            volumes,
            laws,
            tet_law,
            dofs,
            dof_owner,
            pattern,
            scatter,
            symbolic: Arc::new(symbolic),
            diagonal,
            body_force,
            options,
        })
    }

    pub fn node_count(&self) -> usize {
        self.nodes
    }

    pub fn dofs(&self) -> &DofMap {
        &self.dofs
    }

    /// An empty factor of this mesh's tangent pattern, in the ordering and supernodes every solve
    /// uses: what a Newton solve factorizes and preconditions with, for benchmarks of those parts.
    pub fn tangent_factor<T: Precision>(&self) -> TangentFactor<T> {
        TangentFactor::new(self.symbolic.clone())
    }

    /// The tangent on the unknowns (no constraints applied) and the internal force of every node at
    /// `u`; `None` if an element is inverted.
    pub fn linearize(&self, u: &[[f64; 3]]) -> Option<Linearized> {
        let mut values = vec![0.0; self.pattern.row_idx().len()];
        let (_, forces) = self.internal_forces(u, Some(&mut values))?;
        Some((SparseColMat::new(self.pattern.clone(), values), forces))
    }

    fn deformation_gradient(&self, t: usize, u: &[[f64; 3]]) -> Matrix3<f64> {
        let mut f = Matrix3::identity();
        for (a, &n) in self.tets[t].iter().enumerate() {
            let g = self.gradients[t][a];
            let d = u[n as usize];
            for i in 0..3 {
                for j in 0..3 {
                    f[(i, j)] += d[i] * g[j];
                }
            }
        }
        f
    }

    /// Total potential energy Π = Σ V W(F) − f_body·u; `None` if any element is inverted.
    pub fn energy(&self, u: &[[f64; 3]], body_scale: f64) -> Option<f64> {
        let mut strain = 0.0;
        for t in 0..self.tets.len() {
            let law = &self.laws[self.tet_law[t] as usize];
            strain += self.volumes[t] * law.energy(&self.deformation_gradient(t, u))?;
        }
        Some(strain - body_scale * self.body_work(u))
    }

    /// f_body·u at full gravity.
    fn body_work(&self, u: &[[f64; 3]]) -> f64 {
        u.iter()
            .zip(&self.body_force)
            .map(|(d, f)| (0..3).map(|k| d[k] * f[k]).sum::<f64>())
            .sum()
    }

    /// Strain energy Σ V W(F), internal nodal forces ∂Π_int/∂u (all nodes) and, if asked, the
    /// tangent's CSC values, in one pass over the elements; `None` if an element is inverted.
    fn internal_forces(&self, u: &[[f64; 3]], mut tangent: Option<&mut [f64]>) -> Option<(f64, Vec<[f64; 3]>)> {
        let mut forces = vec![[0.0; 3]; self.nodes];
        let mut strain = 0.0;
        if let Some(values) = tangent.as_deref_mut() {
            values.fill(0.0);
        }
        for t in 0..self.tets.len() {
            let law = &self.laws[self.tet_law[t] as usize];
            let response = law.response(&self.deformation_gradient(t, u))?;
            let (g, v) = (&self.gradients[t], self.volumes[t]);
            strain += v * response.energy;
            if let Some(values) = tangent.as_deref_mut() {
                scatter_element_tangent(&response.tangent, g, v, &self.scatter[t], values);
            }
            for (a, &n) in self.tets[t].iter().enumerate() {
                let force = response.stress * Vector3::from(g[a]);
                for i in 0..3 {
                    forces[n as usize][i] += v * force[i];
                }
            }
        }
        Some((strain, forces))
    }

    /// Solves for equilibrium along `load`, cutting load steps where Newton fails.
    pub fn solve(&self, load: Load<'_>) -> Result<Equilibrium, FemError> {
        let started = Instant::now();
        let mut work = Work {
            stats: SolveStats::default(),
            profile: SolveProfile::default(),
            trace: Vec::new(),
            factor: if self.options.reuse_factorization {
                Box::new(self.tangent_factor::<f32>())
            } else {
                Box::new(self.tangent_factor::<f64>())
            },
            tangent: vec![0.0; self.pattern.row_idx().len()],
            refactor: false,
            last_shift: 0.0,
            patch: None,
        };
        let mut initial_step = self.options.initial_step;
        if let Some(elimination) = self.options.elimination
            && !load.prescribed.is_empty()
        {
            let held: Vec<u32> = load.prescribed.iter().map(|&(n, _)| n).collect();
            work.patch = Some(self.patch(&held, elimination.rings));
            initial_step = elimination.initial_step;
        }
        let mut u = load.start.to_vec();
        let mut prescribed = vec![false; self.dofs.len()];
        for &(n, _) in load.prescribed {
            for c in 0..3 {
                if let Some(d) = self.dofs.get(n, c) {
                    prescribed[d] = true;
                }
            }
        }
        let longest = self.options.max_load_step.clamp(1e-6, 1.0);
        let (mut done, mut step) = (0.0f64, initial_step.clamp(1e-6, longest));
        let mut path = Vec::new();
        while done < 1.0 {
            let target = (done + step).min(1.0);
            let mut trial = u.clone();
            let step_index = work.stats.load_steps + work.stats.step_cuts;
            let before = work.trace.len();
            // A grasp's load is the held nodes' motion alone: its work is what the energy gains.
            let grasp = !load.prescribed.is_empty() && load.body_from == load.body_to;
            let stepped = self
                .load_step(&mut trial, &load, &prescribed, (done, target), step_index, &mut work)
                .and_then(|end| {
                    if grasp {
                        self.on_path(&end, done)?;
                    }
                    Ok(end)
                });
            if matches!(stepped, Err(StepFailure::BranchJump)) {
                work.stats.branch_jumps += 1;
            }
            match stepped {
                Ok(StepEnd {
                    load: reached,
                    newton,
                    start,
                    end,
                }) => {
                    tracing::debug!(
                        from = done,
                        to = reached,
                        newton,
                        energy_change = end.energy - start.energy,
                        work_rates = ?(start.rate, end.rate),
                        "load step converged"
                    );
                    u = trial;
                    step = reached - done;
                    done = reached;
                    work.stats.load_steps += 1;
                    if done < 1.0 {
                        path.push(PathState {
                            load: done,
                            displacement: u.clone(),
                        });
                    }
                    if newton <= 4 {
                        step = (step * 1.5).min(longest);
                    }
                }
                Err(failure) => {
                    tracing::debug!(from = done, to = target, "load step cut: {}", failure.describe());
                    work.stats.step_cuts += 1;
                    // Half the step that failed (the last one may have been shorter than `step`).
                    step = (target - done) / 2.0;
                    if work.stats.step_cuts > self.options.max_step_cuts {
                        return Err(FemError::NotConverged {
                            load: target,
                            step: step_index,
                            reason: failure.describe(),
                            residuals: work.trace[before..].iter().map(|i| i.residual).collect(),
                        });
                    }
                }
            }
        }
        let (_, internal) = self.internal_forces(&u, None).ok_or_else(|| FemError::NotConverged {
            load: 1.0,
            step: work.stats.load_steps,
            reason: "the converged state has an inverted element".into(),
            residuals: Vec::new(),
        })?;
        let reactions = load
            .prescribed
            .iter()
            .map(|&(n, _)| {
                std::array::from_fn(|k| internal[n as usize][k] - load.body_to * self.body_force[n as usize][k])
            })
            .collect();
        Ok(Equilibrium {
            displacement: u,
            path,
            reactions,
            stats: work.stats,
            profile: work.profile,
            iterations: work.trace,
            seconds: started.elapsed().as_secs_f64(),
        })
    }

    fn on_path(&self, step: &StepEnd, from: f64) -> Result<(), StepFailure> {
        let length = step.load - from;
        if length > SNAP_STEP && !stays_on_branch(length, step.start, step.end, self.energy_noise) {
            tracing::debug!(from, to = step.load, start = ?step.start, end = ?step.end, "load step jumped branches");
            return Err(StepFailure::BranchJump);
        }
        Ok(())
    }

    /// One load step from `from` towards `to` (load fractions): a tangent predictor that moves the
    /// prescribed nodes, then Newton corrections with line search. A predictor that would invert an
    /// element is shortened (it is linear in the load increment, so no new solve is needed) and the
    /// step ends where it lands. Returns the load reached and the Newton iterations.
    fn load_step(
        &self,
        u: &mut [[f64; 3]],
        load: &Load<'_>,
        prescribed: &[bool],
        (from, to): (f64, f64),
        load_step: usize,
        work: &mut Work,
    ) -> Result<StepEnd, StepFailure> {
        // The held DOFs' whole path, and this step's share of it.
        let mut path = vec![0.0; self.dofs.len()];
        for &(n, target) in load.prescribed {
            for (c, &goal) in target.iter().enumerate() {
                if let Some(d) = self.dofs.get(n, c) {
                    path[d] = goal - load.start[n as usize][c];
                }
            }
        }
        let imposed: Vec<f64> = path.iter().map(|p| (to - from) * p).collect();
        let mut to = to;
        let mut start = None::<PathPoint>;
        // |Δu·r| of the step's first Newton correction: the energy criterion's reference (Bathe).
        let mut first_energy_norm = None::<f64>;
        let mut forcing = Forcing::default();
        for iteration in 0..=self.options.max_iterations {
            let body = load.body_from + to * (load.body_to - load.body_from);
            let mut tangent = std::mem::take(&mut work.tangent);
            let assembled = timed(&mut work.profile.assembly, || {
                self.internal_forces(u, Some(&mut tangent))
            });
            // Only a predictor could leave an inverted state behind, and it is checked.
            let Some((strain, internal)) = assembled else {
                work.stats.inverted_trials += 1;
                return Err(StepFailure::Inverted);
            };
            let mut residual = vec![0.0; self.dofs.len()];
            let (mut external_norm, mut reaction_norm, mut residual_norm) = (0.0f64, 0.0f64, 0.0f64);
            let mut rate = 0.0;
            for (d, &(n, c)) in self.dof_owner.iter().enumerate() {
                let external = body * self.body_force[n as usize][c as usize];
                let r = internal[n as usize][c as usize] - external;
                external_norm += external * external;
                if prescribed[d] {
                    reaction_norm += r * r;
                    rate += r * path[d];
                } else {
                    residual[d] = r;
                    residual_norm += r * r;
                }
            }
            let residual_norm = residual_norm.sqrt();
            let scale = external_norm.sqrt().max(reaction_norm.sqrt()).max(f64::MIN_POSITIVE);
            let energy = strain - body * self.body_work(u);
            let here = PathPoint { energy, rate };
            let start = *start.get_or_insert(here);
            let predictor = iteration == 0;
            let mut rhs: Vec<f64> = (0..self.dofs.len())
                .map(|d| match (prescribed[d], predictor) {
                    (true, true) => imposed[d],
                    (true, false) => 0.0,
                    (false, _) => -residual[d],
                })
                .collect();
            self.constrain(&mut tangent, prescribed, predictor.then_some(&imposed[..]), &mut rhs);
            // The predictor's rhs is the load increment, whose answer sets the step's course.
            let tolerance = if predictor {
                KRYLOV_TOLERANCE
            } else {
                forcing.next(residual_norm)
            };
            let direction = self.direction(&mut tangent, prescribed, &rhs, tolerance, work);
            work.tangent = tangent;
            let direction = direction?;
            let slope: f64 = (0..self.dofs.len()).map(|d| residual[d] * direction[d]).sum();
            let record = |load, step_length| Iteration {
                load_step,
                load,
                residual: residual_norm,
                energy,
                step_length,
            };
            if predictor {
                let fraction = match work.patch.take() {
                    Some(patch) => {
                        let predicted = self.predict_around(&patch, u, &direction, body, scale, work);
                        work.patch = Some(patch);
                        predicted?
                    }
                    None => self.predict(u, &direction, work)?,
                };
                to = from + fraction * (to - from);
                work.trace.push(record(to, fraction));
                continue;
            }
            let energy_norm = slope.abs();
            let reference = *first_energy_norm.get_or_insert(energy_norm);
            let converged = if to < 1.0 {
                residual_norm <= self.options.intermediate_tolerance * scale
            } else {
                residual_norm <= self.options.residual_tolerance * scale
                    && energy_norm <= (self.options.energy_tolerance * reference).max(self.energy_noise)
            };
            if converged {
                // The last correction is below both tolerances; taking it costs nothing.
                self.apply(u, &direction, 1.0);
                if self.energy(u, body).is_none() {
                    self.apply(u, &direction, -1.0);
                }
                return Ok(StepEnd {
                    load: to,
                    newton: iteration - 1,
                    start,
                    end: here,
                });
            }
            if iteration == self.options.max_iterations {
                break;
            }
            work.stats.newton_iterations += 1;
            let length = self.line_search(u, &direction, body, energy, slope, work)?;
            if let Some(patch) = work.patch.take() {
                // The step moved the patch's boundary: its interior follows, to a hundredth of the
                // residual this step started from (a relaxation that stalls still lowered the energy).
                let relaxed = timed(&mut work.profile.elimination, || {
                    self.relax(&patch, u, body, 1e-2 * residual_norm, 0.0)
                });
                work.stats.local_iterations += relaxed.iterations;
                work.patch = Some(patch);
            }
            work.trace.push(record(to, length));
        }
        Err(StepFailure::NotConverged)
    }

    /// Moves `u` along the predictor as far as every element stays well clear of inversion: the
    /// whole way, or [`FEASIBLE_FRACTION`] of the way to where the first element would collapse
    /// (the predictor is linear in the load increment, so the load step ends there and no new
    /// solve is needed). Returns the fraction taken.
    fn predict(&self, u: &mut [[f64; 3]], direction: &[f64], work: &mut Work) -> Result<f64, StepFailure> {
        let limit = timed(&mut work.profile.line_search, || self.feasible_length(u, direction));
        let fraction = (FEASIBLE_FRACTION * limit).min(1.0);
        if fraction < MIN_PREDICTOR_FRACTION {
            work.stats.inverted_trials += 1;
            return Err(StepFailure::Inverted);
        }
        if fraction < 1.0 {
            work.stats.shortened_predictors += 1;
        }
        self.apply(u, direction, fraction);
        Ok(fraction)
    }

    /// The predictor with the graspers' neighbourhood eliminated: the rest of the organ moves along
    /// it as far as its elements stay clear of inversion (the patch's own may fold under the linear
    /// predictor: the patch is solved instead), and the patch follows its moved boundary by local
    /// load steps. Returns the fraction of the predictor taken.
    fn predict_around(
        &self,
        patch: &Patch,
        u: &mut [[f64; 3]],
        direction: &[f64],
        body: f64,
        scale: f64,
        work: &mut Work,
    ) -> Result<f64, StepFailure> {
        let step = self.node_step(direction);
        let limit = timed(&mut work.profile.line_search, || {
            self.feasible_length_of((0..self.tets.len()).filter(|&t| !patch.contains[t]), u, &step)
        });
        let fraction = (FEASIBLE_FRACTION * limit).min(1.0);
        if fraction < MIN_PREDICTOR_FRACTION {
            work.stats.inverted_trials += 1;
            return Err(StepFailure::Inverted);
        }
        let mut goal = u.to_vec();
        self.apply(&mut goal, direction, fraction);
        // Everything outside the patch moves now; the patch (its boundary included) starts where it was.
        let mut next = goal.clone();
        patch.keep(&mut next, u);
        let effort = timed(&mut work.profile.elimination, || {
            self.relax_to(
                patch,
                &mut next,
                &goal,
                body,
                self.options.intermediate_tolerance * scale,
            )
        })
        .ok_or(StepFailure::Eliminated)?;
        work.stats.local_iterations += effort.iterations;
        work.stats.shortened_predictors += usize::from(fraction < 1.0) + effort.shortened;
        u.copy_from_slice(&next);
        Ok(fraction)
    }

    /// A direction in unknowns as a displacement of every node.
    fn node_step(&self, direction: &[f64]) -> Vec<[f64; 3]> {
        let mut step = vec![[0.0; 3]; self.nodes];
        for (d, &(n, c)) in self.dof_owner.iter().enumerate() {
            step[n as usize][c as usize] = direction[d];
        }
        step
    }

    /// The largest step length α ≤ [`FEASIBLE_HORIZON`] along `direction` (in unknowns) before any
    /// element's det(F + α ΔF) reaches zero, or infinity when none does within it: a cubic in α per
    /// element (as libigl's flip-avoiding line search).
    fn feasible_length(&self, u: &[[f64; 3]], direction: &[f64]) -> f64 {
        self.feasible_length_of(0..self.tets.len(), u, &self.node_step(direction))
    }

    /// [`Hyperelastic::feasible_length`] over `elements`, for a displacement `step` of every node.
    fn feasible_length_of(&self, elements: impl Iterator<Item = usize>, u: &[[f64; 3]], step: &[[f64; 3]]) -> f64 {
        elements
            .filter_map(|t| {
                let f = self.deformation_gradient(t, u);
                let df = self.deformation_gradient(t, step) - Matrix3::identity();
                first_root_of_determinant(&f, &df, FEASIBLE_HORIZON)
            })
            .fold(f64::INFINITY, f64::min)
    }

    /// Applies the prescribed DOFs to the tangent: their rows and columns become identity, and the
    /// columns' coupling to the free DOFs moves to the right-hand side when they move (predictor).
    fn constrain(&self, values: &mut [f64], prescribed: &[bool], imposed: Option<&[f64]>, rhs: &mut [f64]) {
        let (col_ptr, rows) = (self.pattern.col_ptr(), self.pattern.row_idx());
        for col in 0..self.dofs.len() {
            for p in col_ptr[col]..col_ptr[col + 1] {
                let row = rows[p];
                if prescribed[col]
                    && !prescribed[row]
                    && let Some(imposed) = imposed
                {
                    rhs[row] -= values[p] * imposed[col];
                }
                if prescribed[col] || prescribed[row] {
                    values[p] = if row == col { 1.0 } else { 0.0 };
                }
            }
        }
    }

    /// Solves the constrained tangent system by conjugate gradients against the factor of an
    /// earlier tangent (with the graspers' neighbourhood, where the elimination moves the state most,
    /// solved exactly in the preconditioner: [`PatchBlock`]), factorizing this one first when there
    /// is none or it has grown stale. Where
    /// the tangent is not positive definite (compressed or buckling tissue far from equilibrium), CG
    /// stops at the negative curvature with a descent direction (truncated Newton), which costs far
    /// less than factorizing a shifted tangent. Without reuse, each tangent is factorized in f64 and
    /// solved exactly.
    fn direction(
        &self,
        values: &mut [f64],
        prescribed: &[bool],
        rhs: &[f64],
        tolerance: f64,
        work: &mut Work,
    ) -> Result<Vec<f64>, StepFailure> {
        let mut x = rhs.to_vec();
        if !self.options.reuse_factorization {
            self.factorize(values, prescribed, work)?;
            let factor = &mut work.factor;
            timed(&mut work.profile.linear_solve, || factor.solve_in_place(&mut x));
            return Ok(x);
        }
        let fresh = !work.factor.is_valid() || work.refactor;
        if fresh {
            self.factorize(values, prescribed, work)?;
            work.refactor = false;
        }
        let matrix = SparseColMatRef::new(self.pattern.as_ref(), values);
        let factor = &mut work.factor;
        // A fresh factor is the tangent's own: the patch's block would add nothing to it.
        let block = work
            .patch
            .as_ref()
            .filter(|_| !fresh)
            .and_then(|patch| PatchBlock::new(patch, matrix));
        let outcome = timed(&mut work.profile.linear_solve, || match &block {
            Some(block) => conjugate_gradients(matrix, rhs, &mut x, tolerance, MAX_KRYLOV_ITERATIONS, &mut |z| {
                block.precondition(matrix, factor.as_mut(), z)
            }),
            None => conjugate_gradients(matrix, rhs, &mut x, tolerance, MAX_KRYLOV_ITERATIONS, &mut |z| {
                factor.solve_in_place(z)
            }),
        });
        tracing::debug!(?outcome, fresh, "conjugate gradients");
        match outcome {
            Krylov::Converged(iterations) | Krylov::NegativeCurvature(iterations) => {
                work.stats.krylov_iterations += iterations;
                work.refactor = !fresh && iterations > REFACTOR_AFTER;
            }
            Krylov::Stalled if fresh => {
                // Even this tangent's own (f32, possibly shifted) factor leaves CG short: its
                // preconditioned right-hand side is still a descent direction.
                work.stats.krylov_iterations += MAX_KRYLOV_ITERATIONS;
                x.copy_from_slice(rhs);
                let factor = &mut work.factor;
                timed(&mut work.profile.linear_solve, || factor.solve_in_place(&mut x));
            }
            Krylov::Stalled => {
                work.stats.krylov_iterations += MAX_KRYLOV_ITERATIONS;
                work.refactor = true;
                return self.direction(values, prescribed, rhs, tolerance, work);
            }
        }
        // Prescribed rows are identity rows decoupled from the rest: their exact value is the
        // right-hand side, which an inexact solve only approaches.
        for (d, _) in prescribed.iter().enumerate().filter(|(_, held)| **held) {
            x[d] = rhs[d];
        }
        Ok(x)
    }

    /// Cholesky of the constrained tangent, shifting its free diagonal (a Levenberg-style
    /// regularization that keeps the correction a descent direction) when it is not positive
    /// definite. A shift starts at 1e-4 of the mean diagonal, or a hundredth of the solve's last
    /// one if larger, and grows tenfold.
    fn factorize(&self, values: &mut [f64], prescribed: &[bool], work: &mut Work) -> Result<(), StepFailure> {
        let mean_diagonal =
            self.diagonal.iter().map(|&p| values[p].abs()).sum::<f64>() / self.diagonal.len().max(1) as f64;
        let (mut shift, mut attempt) = (0.0, 0);
        loop {
            let matrix = SparseColMatRef::new(self.pattern.as_ref(), values);
            work.stats.factorizations += 1;
            let factor = &mut work.factor;
            match timed(&mut work.profile.factorization, || factor.factorize(matrix)) {
                Ok(()) => {
                    if shift > 0.0 {
                        work.last_shift = shift;
                    }
                    return Ok(());
                }
                Err(e) if attempt == MAX_SHIFTS => return Err(StepFailure::Factorization(format!("{e:?}"))),
                Err(_) => {
                    if attempt == 0 {
                        work.stats.shifted_factorizations += 1;
                    }
                    let next = if shift == 0.0 {
                        (1e-4 * mean_diagonal).max(0.01 * work.last_shift)
                    } else {
                        10.0 * shift
                    };
                    for (d, &p) in self.diagonal.iter().enumerate() {
                        if !prescribed[d] {
                            values[p] += next - shift;
                        }
                    }
                    shift = next;
                }
            }
            attempt += 1;
        }
    }

    fn apply(&self, u: &mut [[f64; 3]], direction: &[f64], length: f64) {
        for (d, &(n, c)) in self.dof_owner.iter().enumerate() {
            u[n as usize][c as usize] += length * direction[d];
        }
    }

    /// Backtracking (Armijo) on the potential energy; states with an inverted element count as
    /// infinitely expensive. Leaves `u` at the accepted point and returns the step length.
    fn line_search(
        &self,
        u: &mut [[f64; 3]],
        direction: &[f64],
        body: f64,
        energy: f64,
        slope: f64,
        work: &mut Work,
    ) -> Result<f64, StepFailure> {
        let base = u.to_vec();
        let limit = timed(&mut work.profile.line_search, || self.feasible_length(u, direction));
        let mut length = (FEASIBLE_FRACTION * limit).min(1.0);
        // Near convergence the energy change sinks below round-off: accept changes within it.
        let tolerance = self.energy_noise;
        for _ in 0..12 {
            u.copy_from_slice(&base);
            self.apply(u, direction, length);
            match timed(&mut work.profile.line_search, || self.energy(u, body)) {
                Some(e) if e <= energy + 1e-4 * length * slope + tolerance => return Ok(length),
                Some(_) => {}
                None => work.stats.inverted_trials += 1,
            }
            length /= 2.0;
        }
        u.copy_from_slice(&base);
        Err(StepFailure::LineSearch)
    }
}

/// (node a, node b, component i, component j) in the row-major order of a 12×12 element matrix.
fn element_entries() -> impl Iterator<Item = (usize, usize, usize, usize)> {
    (0..144).map(|e| {
        let (row, col) = (e / 12, e % 12);
        (row / 3, col / 3, row % 3, col % 3)
    })
}

/// Adds `K_ai,bk = V Σ_JL A_iJ,kL ∂_J N_a ∂_L N_b` into the CSC values.
fn scatter_element_tangent(a: &TangentTerms, g: &[Vec3; 4], volume: f64, scatter: &[u32; 144], values: &mut [f64]) {
    let nodes = g.map(|g| a.node(&g));
    // The element matrix is symmetric (A is): only blocks a ≤ b are computed, and each entry of
    // the upper triangle goes to both places.
    for na in 0..4 {
        for nb in na..4 {
            let block = volume * a.element_block(&nodes[na], &nodes[nb]);
            for i in 0..3 {
                let first_k = if na == nb { i } else { 0 };
                for k in first_k..3 {
                    let (row, col) = (3 * na + i, 3 * nb + k);
                    let (upper, lower) = (scatter[12 * row + col], scatter[12 * col + row]);
                    if upper != u32::MAX {
                        values[upper as usize] += block[(i, k)];
                    }
                    if lower != u32::MAX && row != col {
                        values[lower as usize] += block[(i, k)];
                    }
                }
            }
        }
    }
}

/// Whether a load step of `length` (a load fraction) from `start` to `end` stayed on its equilibrium
/// branch. Along one, dΠ/dλ is the graspers' rate of work R·D, so the energy gained is its integral
/// over the step; while that rate moves between its values at the step's two ends, the integral is
/// at least the step times the smaller one. A snap to another branch releases energy the path never
/// did work for and falls below that. But a snap also drops the rate, so where the rate fell the
/// smaller one is the snap's own: there the gain is held to the trapezoid of the two rates instead.
fn stays_on_branch(length: f64, start: PathPoint, end: PathPoint, energy_noise: f64) -> bool {
    let least = if end.rate < start.rate {
        let trapezoid = length * (start.rate + end.rate) / 2.0;
        trapezoid - SOFTENING_TOLERANCE * trapezoid.abs()
    } else {
        let least = length * start.rate;
        least - PATH_TOLERANCE * least.abs()
    };
    end.energy - start.energy >= least - energy_noise
}

/// The smallest α in (0, `horizon`] at which det(F + α ΔF) ≤ 0, if any, for det F > 0, from below
/// (det is still positive there). det(F + αΔF) = det F + α⟨cof F, ΔF⟩ + α²⟨F, cof ΔF⟩ + α³ det ΔF;
/// between the roots of its derivative it is monotone, so the first such piece whose right end is
/// not positive holds the root, found by bisection.
fn first_root_of_determinant(f: &Matrix3<f64>, df: &Matrix3<f64>, horizon: f64) -> Option<f64> {
    let cofactor = |m: &Matrix3<f64>| {
        Matrix3::from_fn(|i, j| {
            let (r0, r1) = ((i + 1) % 3, (i + 2) % 3);
            let (c0, c1) = ((j + 1) % 3, (j + 2) % 3);
            m[(r0, c0)] * m[(r1, c1)] - m[(r0, c1)] * m[(r1, c0)]
        })
    };
    let c = [
        f.determinant(),
        cofactor(f).component_mul(df).sum(),
        cofactor(df).component_mul(f).sum(),
        df.determinant(),
    ];
    let p = |a: f64| c[0] + a * (c[1] + a * (c[2] + a * c[3]));
    // Critical points: 3 c3 a² + 2 c2 a + c1 = 0.
    // Called for every element at every step: the piece ends live on the stack.
    let mut ends = [horizon; 3];
    let mut inside = 0;
    for a in quadratic_roots(3.0 * c[3], 2.0 * c[2], c[1]).into_iter().flatten() {
        if a > 0.0 && a < horizon {
            ends[inside] = a;
            inside += 1;
        }
    }
    ends[..inside].sort_by(f64::total_cmp);
    let mut left = 0.0;
    for &right in &ends[..=inside] {
        if p(right) <= 0.0 {
            let (mut low, mut high) = (left, right);
            for _ in 0..60 {
                let mid = 0.5 * (low + high);
                if p(mid) > 0.0 {
                    low = mid;
                } else {
                    high = mid;
                }
            }
            return Some(low);
        }
        left = right;
    }
    None
}

/// The real roots of a x² + b x + c (of b x + c when a vanishes against b and c).
fn quadratic_roots(a: f64, b: f64, c: f64) -> [Option<f64>; 2] {
    if a.abs() <= 1e-14 * (b.abs() + c.abs()) {
        return [(b != 0.0).then(|| -c / b), None];
    }
    let discriminant = b * b - 4.0 * a * c;
    if discriminant < 0.0 {
        return [None, None];
    }
    // The stable pair: no cancellation between b and the root of the discriminant.
    let q = -0.5 * (b + b.signum() * discriminant.sqrt());
    if q == 0.0 {
        return [Some(0.0), None];
    }
    [Some(q / a), Some(c / q)]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The load steps of sample 7 of seed 3 (`nak datagen --regime nonlinear --single 8 --multi 8
    /// --seed 3`) and of a sample of seed 7 as the solver logged them (`RUST_LOG=nak::fem=debug`).
    #[test]
    fn a_load_step_that_snaps_to_another_branch_is_told_from_one_that_softens() {
        let point = |energy, rate| PathPoint { energy, rate };
        let on = |length, start, end| stays_on_branch(length, start, end, 0.0);
        // A stiffening step on the path gains more than its least rate of work.
        assert!(on(0.3, point(0.0, 0.0872), point(0.0427, 0.1899)));
        // A snap from 50 % to 80 % of the grasp: the rate fell, and the 54.79 mJ gained are 1.9 %
        // short of the trapezoid, though above the step times the snap's own (lowest) rate, 54.71 mJ.
        // Steps of 2 % stay on the path, where the rate rises to 0.21.
        let snap = (point(0.0, 0.18994), point(0.05479, 0.18235));
        assert!(!on(0.3, snap.0, snap.1));
        // A smooth softening of 16 % over 45 % of the grasp gains its trapezoid within 0.6 %.
        assert!(on(0.45, point(0.0, 1.0), point(0.45 * 0.92 * 0.994, 0.84)));
        // A snap that raises the energy less than the least work done on the way.
        assert!(!on(0.3, point(0.0, 0.184), point(0.0516, 0.21)));
    }

    #[test]
    fn the_first_root_of_a_determinant_is_where_the_element_collapses() {
        // Compressing x by α: det = 1 − α, collapsing at α = 1.
        let squash = Matrix3::from_diagonal(&Vector3::new(-1.0, 0.0, 0.0));
        let at = first_root_of_determinant(&Matrix3::identity(), &squash, 2.0).unwrap();
        assert!((at - 1.0).abs() < 1e-12 && at <= 1.0, "{at}");
        // Two axes at different rates: (1 − 2α)(1 − α/2) first vanishes at α = ½.
        let two = Matrix3::from_diagonal(&Vector3::new(-2.0, -0.5, 0.0));
        let at = first_root_of_determinant(&Matrix3::identity(), &two, 2.0).unwrap();
        assert!((at - 0.5).abs() < 1e-12, "{at}");
        // Growing first, then collapsing: (1 + α)(1 − 1.5α) has its critical point before its root.
        let late = Matrix3::from_diagonal(&Vector3::new(1.0, -1.5, 0.0));
        let at = first_root_of_determinant(&Matrix3::identity(), &late, 2.0).unwrap();
        assert!((at - 2.0 / 3.0).abs() < 1e-12, "{at}");
        // Stretching and rotating never collapses.
        let stretch = Matrix3::new(0.5, 0.2, 0.0, -0.2, 0.5, 0.0, 0.0, 0.0, 1.0);
        assert_eq!(first_root_of_determinant(&Matrix3::identity(), &stretch, 2.0), None);
        // Beyond the horizon is not looked at.
        assert_eq!(first_root_of_determinant(&Matrix3::identity(), &squash, 0.5), None);
    }

    #[test]
    fn forcing_is_loose_far_from_the_solution_and_tight_near_it() {
        let mut forcing = Forcing::default();
        assert_eq!(forcing.next(1.0), KRYLOV_TOLERANCE_FAR);
        // A residual that barely falls keeps the linear solves loose ...
        assert_eq!(forcing.next(0.9), KRYLOV_TOLERANCE_FAR);
        // ... one that halves asks for 0.9 · 0.5² ...
        assert!((forcing.next(0.45) - 0.225).abs() < 1e-12);
        // ... and a fast fall for the floor.
        assert_eq!(forcing.next(0.0045), KRYLOV_TOLERANCE);
        assert_eq!(forcing.next(0.0), KRYLOV_TOLERANCE);
    }
}
