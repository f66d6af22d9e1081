//! Total-Lagrangian P1 finite elements with compressible Mooney–Rivlin (DESIGN.md §4), solved by
//! Newton–Raphson with the consistent tangent, a backtracking line search on the potential energy and
//! adaptive load stepping.
//!
//! The unknowns are every DOF of every node that is not `fixed`; prescribed (grasped) DOFs stay in the
//! system as identity rows. The sparsity pattern is therefore the same for every grasp, and the
//! symbolic Cholesky factorization is computed once per mesh.

use std::time::Instant;

use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::{SparseColMat, SymbolicSparseColMat, Triplet};
use faer::{Mat, Side};
use nalgebra::Matrix3;
use serde::{Deserialize, Serialize};

use super::FemError;
use super::hyperelastic::{MooneyRivlin, Tangent};
use super::linear::{DofMap, shape_gradients};
use crate::mesh::TetMesh;
use crate::mesh::topology::Vec3;

/// How hard the solver tries; the defaults suit the phantom's grasps.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NewtonOptions {
    /// Converged when ‖residual‖ ≤ this × the larger of ‖external force‖ and ‖reactions‖ ...
    pub residual_tolerance: f64,
    /// ... and the energy increment |Δu·r| ≤ this × the load step's first one.
    pub energy_tolerance: f64,
    /// Newton iterations per load step before the step is cut.
    pub max_iterations: usize,
    /// The first load step, as a fraction of the whole load.
    pub initial_step: f64,
    /// Load-step halvings before the solve is declared failed.
    pub max_step_cuts: usize,
}

impl Default for NewtonOptions {
    fn default() -> Self {
        Self {
            residual_tolerance: 1e-6,
            energy_tolerance: 1e-12,
            max_iterations: 25,
            initial_step: 1.0,
            max_step_cuts: 12,
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
    /// Factorizations that needed a diagonal shift because the tangent was not positive definite.
    pub shifted_factorizations: usize,
}

/// A converged equilibrium: displacement of every node from the reference configuration.
#[derive(Debug, Clone)]
pub struct Equilibrium {
    pub displacement: Vec<[f64; 3]>,
    /// Force the constraints exert on each prescribed node, in the order given.
    pub reactions: Vec<[f64; 3]>,
    pub stats: SolveStats,
    pub iterations: Vec<Iteration>,
    pub seconds: f64,
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

/// Why a load step failed; the solver cuts the step and retries until it runs out of cuts.
enum StepFailure {
    Inverted,
    LineSearch,
    NotConverged,
    Factorization(String),
}

impl StepFailure {
    fn describe(&self) -> String {
        match self {
            Self::Inverted => "an element inverted (J ≤ 0)".into(),
            Self::LineSearch => "the line search found no energy decrease".into(),
            Self::NotConverged => "Newton did not converge in the allowed iterations".into(),
            Self::Factorization(e) => format!("the tangent could not be factorized ({e})"),
        }
    }
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
    symbolic: SymbolicLlt<usize>,
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
            .map(MooneyRivlin::from_material)
            .collect();
        let fixed = mesh.node_sets.get("fixed").cloned().unwrap_or_default();
        let dofs = DofMap::without(mesh.node_count(), &fixed);
        let mut dof_owner = vec![(0, 0); dofs.len()];
        for n in 0..mesh.node_count() as u32 {
            for c in 0..3 {
                if let Some(d) = dofs.get(n, c) {
                    dof_owner[d] = (n, c as u8);
                }
            }
        }
        let body = &mesh.config.body;
        let mut body_force = vec![[0.0; 3]; mesh.node_count()];
        let mut gradients = Vec::with_capacity(mesh.tets.len());
        let mut volumes = Vec::with_capacity(mesh.tets.len());
        let mut triplets = Vec::with_capacity(mesh.tets.len() * 144);
        for (t, tet) in mesh.tets.iter().enumerate() {
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
        let scatter = mesh
            .tets
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
        let symbolic = SymbolicLlt::try_new(pattern.as_ref(), Side::Lower)
            .map_err(|e| FemError::Assembly(format!("symbolic factorization: {e:?}")))?;
        // Every element couples each of its DOFs with itself, so every diagonal entry exists.
        let diagonal = (0..n).map(|d| find(&pattern, d, d).unwrap_or(usize::MAX)).collect();
        // Each element energy is a sum of terms of size ~V(3 C10 + 3 C01 + κ), each exact to ~1e-16.
        let energy_noise = 1e-13
            * mesh
                .tet_region
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
            tets: mesh.tets.clone(),
            gradients,
            volumes,
            laws,
            tet_law: mesh.tet_region.clone(),
            dofs,
            dof_owner,
            pattern,
            scatter,
            symbolic,
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
            let f = self.deformation_gradient(t, u);
            let (g, v) = (&self.gradients[t], self.volumes[t]);
            strain += v * law.energy(&f)?;
            let p = match tangent {
                Some(ref mut values) => {
                    let (p, a) = law.stress_and_tangent(&f)?;
                    scatter_element_tangent(&a, g, v, &self.scatter[t], values);
                    p
                }
                None => law.stress(&f)?,
            };
            for (a, &n) in self.tets[t].iter().enumerate() {
                for i in 0..3 {
                    forces[n as usize][i] += v * (0..3).map(|j| p[(i, j)] * g[a][j]).sum::<f64>();
                }
            }
        }
        Some((strain, forces))
    }

    /// Solves for equilibrium along `load`, cutting load steps where Newton fails.
    pub fn solve(&self, load: Load<'_>) -> Result<Equilibrium, FemError> {
        let started = Instant::now();
        let mut stats = SolveStats::default();
        let mut iterations = Vec::new();
        let mut u = load.start.to_vec();
        let mut prescribed = vec![false; self.dofs.len()];
        for &(n, _) in load.prescribed {
            for c in 0..3 {
                if let Some(d) = self.dofs.get(n, c) {
                    prescribed[d] = true;
                }
            }
        }
        let (mut done, mut step) = (0.0f64, self.options.initial_step.clamp(1e-6, 1.0));
        while done < 1.0 {
            let target = (done + step).min(1.0);
            let mut trial = u.clone();
            let step_index = stats.load_steps + stats.step_cuts;
            let before = iterations.len();
            match self.load_step(
                &mut trial,
                &load,
                &prescribed,
                (done, target),
                step_index,
                &mut stats,
                &mut iterations,
            ) {
                Ok(newton) => {
                    tracing::debug!(from = done, to = target, newton, "load step converged");
                    u = trial;
                    done = target;
                    stats.load_steps += 1;
                    if newton <= 4 {
                        step = (step * 1.5).min(1.0);
                    }
                }
                Err(failure) => {
                    tracing::debug!(from = done, to = target, "load step cut: {}", failure.describe());
                    stats.step_cuts += 1;
                    step /= 2.0;
                    if stats.step_cuts > self.options.max_step_cuts {
                        return Err(FemError::NotConverged {
                            load: target,
                            step: step_index,
                            reason: failure.describe(),
                            residuals: iterations[before..].iter().map(|i| i.residual).collect(),
                        });
                    }
                }
            }
        }
        let (_, internal) = self.internal_forces(&u, None).ok_or_else(|| FemError::NotConverged {
            load: 1.0,
            step: stats.load_steps,
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
            reactions,
            stats,
            iterations,
            seconds: started.elapsed().as_secs_f64(),
        })
    }

    /// One load step from `from` to `to` (load fractions): a tangent predictor that moves the
    /// prescribed nodes, then Newton corrections with line search. Returns the Newton iterations.
    #[allow(clippy::too_many_arguments)]
    fn load_step(
        &self,
        u: &mut [[f64; 3]],
        load: &Load<'_>,
        prescribed: &[bool],
        (from, to): (f64, f64),
        load_step: usize,
        stats: &mut SolveStats,
        trace: &mut Vec<Iteration>,
    ) -> Result<usize, StepFailure> {
        let body = load.body_from + to * (load.body_to - load.body_from);
        let mut imposed = vec![0.0; self.dofs.len()];
        for &(n, target) in load.prescribed {
            for (c, &goal) in target.iter().enumerate() {
                if let Some(d) = self.dofs.get(n, c) {
                    let start = load.start[n as usize][c];
                    imposed[d] = (to - from) * (goal - start);
                }
            }
        }
        // |Δu·r| of the step's first Newton correction: the energy criterion's reference (Bathe).
        let mut first_energy_norm = None::<f64>;
        let mut values = vec![0.0; self.pattern.row_idx().len()];
        for iteration in 0..=self.options.max_iterations {
            // Only the predictor can leave an inverted state behind (the line search rejects them).
            let Some((strain, internal)) = self.internal_forces(u, Some(&mut values)) else {
                stats.inverted_trials += 1;
                return Err(StepFailure::Inverted);
            };
            let mut residual = vec![0.0; self.dofs.len()];
            let (mut external_norm, mut reaction_norm, mut residual_norm) = (0.0f64, 0.0f64, 0.0f64);
            for (d, &(n, c)) in self.dof_owner.iter().enumerate() {
                let external = body * self.body_force[n as usize][c as usize];
                let r = internal[n as usize][c as usize] - external;
                external_norm += external * external;
                if prescribed[d] {
                    reaction_norm += r * r;
                } else {
                    residual[d] = r;
                    residual_norm += r * r;
                }
            }
            let residual_norm = residual_norm.sqrt();
            let scale = external_norm.sqrt().max(reaction_norm.sqrt()).max(f64::MIN_POSITIVE);
            let energy = strain - body * self.body_work(u);
            let predictor = iteration == 0;
            let mut rhs = Mat::<f64>::zeros(self.dofs.len(), 1);
            for d in 0..self.dofs.len() {
                rhs[(d, 0)] = match (prescribed[d], predictor) {
                    (true, true) => imposed[d],
                    (true, false) => 0.0,
                    (false, _) => -residual[d],
                };
            }
            self.constrain(&mut values, prescribed, predictor.then_some(&imposed[..]), &mut rhs);
            let direction = self.factorize_and_solve(&mut values, prescribed, rhs, stats)?;
            let slope: f64 = (0..self.dofs.len()).map(|d| residual[d] * direction[d]).sum();
            let mut record = |step_length| {
                trace.push(Iteration {
                    load_step,
                    load: to,
                    residual: residual_norm,
                    energy,
                    step_length,
                })
            };
            if predictor {
                self.apply(u, &direction, 1.0);
                record(1.0);
                continue;
            }
            let energy_norm = slope.abs();
            let reference = *first_energy_norm.get_or_insert(energy_norm);
            if residual_norm <= self.options.residual_tolerance * scale
                && energy_norm <= (self.options.energy_tolerance * reference).max(self.energy_noise)
            {
                // The last correction is below both tolerances; taking it costs nothing.
                self.apply(u, &direction, 1.0);
                if self.energy(u, body).is_none() {
                    self.apply(u, &direction, -1.0);
                }
                return Ok(iteration - 1);
            }
            if iteration == self.options.max_iterations {
                break;
            }
            stats.newton_iterations += 1;
            let length = self.line_search(u, &direction, body, energy, slope, stats)?;
            record(length);
        }
        Err(StepFailure::NotConverged)
    }

    /// Applies the prescribed DOFs to the tangent: their rows and columns become identity, and the
    /// columns' coupling to the free DOFs moves to the right-hand side when they move (predictor).
    fn constrain(&self, values: &mut [f64], prescribed: &[bool], imposed: Option<&[f64]>, rhs: &mut Mat<f64>) {
        let (col_ptr, rows) = (self.pattern.col_ptr(), self.pattern.row_idx());
        for col in 0..self.dofs.len() {
            for p in col_ptr[col]..col_ptr[col + 1] {
                let row = rows[p];
                if prescribed[col]
                    && !prescribed[row]
                    && let Some(imposed) = imposed
                {
                    rhs[(row, 0)] -= values[p] * imposed[col];
                }
                if prescribed[col] || prescribed[row] {
                    values[p] = if row == col { 1.0 } else { 0.0 };
                }
            }
        }
    }

    /// Cholesky of the constrained tangent, shifting its free diagonal (a Levenberg-style
    /// regularization that keeps the direction a descent one) when it is not positive definite.
    fn factorize_and_solve(
        &self,
        values: &mut [f64],
        prescribed: &[bool],
        mut rhs: Mat<f64>,
        stats: &mut SolveStats,
    ) -> Result<Vec<f64>, StepFailure> {
        let diagonal = &self.diagonal;
        let mean_diagonal = diagonal.iter().map(|&p| values[p].abs()).sum::<f64>() / diagonal.len().max(1) as f64;
        let mut shift = 0.0;
        for attempt in 0..12 {
            let matrix = faer::sparse::SparseColMatRef::new(self.pattern.as_ref(), values);
            match Llt::try_new_with_symbolic(self.symbolic.clone(), matrix, Side::Lower) {
                Ok(factor) => {
                    factor.solve_in_place(rhs.as_mut());
                    return Ok((0..self.dofs.len()).map(|d| rhs[(d, 0)]).collect());
                }
                Err(e) if attempt == 11 => return Err(StepFailure::Factorization(format!("{e:?}"))),
                Err(_) => {
                    if attempt == 0 {
                        stats.shifted_factorizations += 1;
                    }
                    let next = if shift == 0.0 {
                        1e-6 * mean_diagonal
                    } else {
                        10.0 * shift
                    };
                    for (d, &p) in diagonal.iter().enumerate() {
                        if !prescribed[d] {
                            values[p] += next - shift;
                        }
                    }
                    shift = next;
                }
            }
        }
        Err(StepFailure::Factorization(
            "no shift made the tangent positive definite".into(),
        ))
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
        stats: &mut SolveStats,
    ) -> Result<f64, StepFailure> {
        let base = u.to_vec();
        let mut length = 1.0;
        // Near convergence the energy change sinks below round-off: accept changes within it.
        let tolerance = self.energy_noise;
        for _ in 0..12 {
            u.copy_from_slice(&base);
            self.apply(u, direction, length);
            match self.energy(u, body) {
                Some(e) if e <= energy + 1e-4 * length * slope + tolerance => return Ok(length),
                Some(_) => {}
                None => stats.inverted_trials += 1,
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
fn scatter_element_tangent(a: &Tangent, g: &[Vec3; 4], volume: f64, scatter: &[u32; 144], values: &mut [f64]) {
    // m[node][i][k][L] = Σ_J ∂_J N_a A_iJ,kL, then contracted with ∂_L N_b.
    let mut m = [[[[0.0; 3]; 3]; 3]; 4];
    for (node, m) in m.iter_mut().enumerate() {
        for i in 0..3 {
            for k in 0..3 {
                for l in 0..3 {
                    m[i][k][l] = (0..3).map(|j| g[node][j] * a[3 * i + j][3 * k + l]).sum();
                }
            }
        }
    }
    for (e, &slot) in scatter.iter().enumerate() {
        if slot == u32::MAX {
            continue;
        }
        let (row, col) = (e / 12, e % 12);
        let (na, i, nb, k) = (row / 3, row % 3, col / 3, col % 3);
        values[slot as usize] += volume * (0..3).map(|l| m[na][i][k][l] * g[nb][l]).sum::<f64>();
    }
}
