//! Nonlinear elimination around the graspers (Cai and Keyes' idea, in the form Hwang, Cai and Li
//! give it for locally nonlinear problems): the nodes within a few rings of the held ones are solved
//! exactly, alone, with the rest of the organ held where it is, after every global Newton step and
//! after every predictor.
//!
//! Why: a grasp moves four to eight nodes by up to 9 cm, and on the phantom 75–100 % of the
//! residual's square sits in the first ring of nodes around them at every global iteration. Global
//! Newton then crawls, its steps limited by the few elements there that the barrier keeps from
//! collapsing. Solved alone, that patch is a few hundred unknowns: a dense Cholesky factorization of
//! its Hessian costs about a millisecond, against 100 ms for the whole tangent.

use faer::linalg::solvers::Solve;
use faer::sparse::SparseColMatRef;
use faer::{Mat, Side};
use nalgebra::Vector3;

use super::{FEASIBLE_FRACTION, Hyperelastic, MIN_PREDICTOR_FRACTION};
use crate::fem::factor::Factor;

/// Newton iterations one relaxation of the patch may take.
const MAX_LOCAL_ITERATIONS: usize = 25;
/// Halvings of a local load step before the patch is declared unsolvable.
const MAX_LOCAL_CUTS: usize = 16;
/// Local load steps before the last end at this multiple of the final tolerance.
const LOCAL_INTERMEDIATE: f64 = 10.0;
/// Below this fraction of the element forces it sums, a gradient is round-off.
const ROUND_OFF: f64 = 1e-12;
/// A relaxation after a local predictor is done when its gradient has fallen this far, whatever the
/// absolute tolerance (which is zero where a grasp starts from an unloaded body).
const LOCAL_REDUCTION: f64 = 1e-3;

/// The nodes solved alone, and the elements they touch.
pub(super) struct Patch {
    /// Nodes whose DOFs the patch solves for: within the rings, neither held nor fixed.
    interior: Vec<u32>,
    /// Each node's position in `interior`, or `u32::MAX`.
    index: Vec<u32>,
    /// Elements with an interior node.
    elements: Vec<u32>,
    /// Whether each element of the mesh is one of `elements`.
    pub contains: Vec<bool>,
    /// The other nodes of `elements`: held, fixed, or just outside the rings.
    boundary: Vec<u32>,
    /// The unknowns of the interior nodes, in the global numbering, three per node.
    unknowns: Vec<usize>,
    /// Each global unknown's position in `unknowns`, or `u32::MAX`.
    local_unknown: Vec<u32>,
}

/// The patch's block of the global tangent, factorized: with the factor of an earlier tangent, a
/// preconditioner that is exact where the tangent changed most since (see [`PatchBlock::precondition`]).
pub(super) struct PatchBlock<'a> {
    patch: &'a Patch,
    block: faer::linalg::solvers::Llt<f64>,
}

/// How one relaxation of a patch ended.
#[derive(Debug, Clone, Copy)]
pub(super) struct Relaxed {
    pub iterations: usize,
    /// Whether the gradient reached the tolerance (else Newton stalled, or the patch started inverted).
    pub converged: bool,
}

/// What solving a patch took.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct LocalEffort {
    pub iterations: usize,
    pub shortened: usize,
}

/// The dense gradient and Hessian of the energy over a patch's interior DOFs.
struct LocalSystem {
    hessian: Mat<f64>,
    gradient: Vec<f64>,
    /// −H_IB Δb: what moving the boundary by `moved` does to the interior's equations.
    coupling: Vec<f64>,
    /// The sum of the magnitudes of the element forces the gradient adds up: its round-off is
    /// about 1e-16 of this.
    magnitude: f64,
}

impl LocalSystem {
    fn new(dofs: usize) -> Self {
        Self {
            hessian: Mat::zeros(dofs, dofs),
            gradient: vec![0.0; dofs],
            coupling: vec![0.0; dofs],
            magnitude: 0.0,
        }
    }

    /// H x = rhs by Cholesky, shifting the diagonal (tenfold from 1e-4 of its mean) where H is not
    /// positive definite.
    fn solve(&self, rhs: &[f64]) -> Option<Vec<f64>> {
        let n = rhs.len();
        let mean = (0..n).map(|i| self.hessian[(i, i)].abs()).sum::<f64>() / n.max(1) as f64;
        let mut shift = 0.0;
        for _ in 0..10 {
            let mut shifted = self.hessian.clone();
            for i in 0..n {
                shifted[(i, i)] += shift;
            }
            if let Ok(llt) = shifted.llt(Side::Lower) {
                let mut x = Mat::<f64>::from_fn(n, 1, |i, _| rhs[i]);
                llt.solve_in_place(x.as_mut());
                return Some((0..n).map(|i| x[(i, 0)]).collect());
            }
            shift = if shift == 0.0 { 1e-4 * mean } else { 10.0 * shift };
        }
        None
    }
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

impl Hyperelastic {
    /// The patch of the nodes within `rings` element rings of `held`.
    pub(super) fn patch(&self, held: &[u32], rings: usize) -> Patch {
        let mut ring = vec![u32::MAX; self.nodes];
        for &n in held {
            ring[n as usize] = 0;
        }
        for level in 1..=rings as u32 {
            for tet in &self.tets {
                if tet.iter().any(|&n| ring[n as usize] == level - 1) {
                    for &n in tet {
                        if ring[n as usize] == u32::MAX {
                            ring[n as usize] = level;
                        }
                    }
                }
            }
        }
        let interior: Vec<u32> = (0..self.nodes as u32)
            .filter(|&n| (1..=rings as u32).contains(&ring[n as usize]) && self.dofs.get(n, 0).is_some())
            .collect();
        let mut index = vec![u32::MAX; self.nodes];
        for (i, &n) in interior.iter().enumerate() {
            index[n as usize] = i as u32;
        }
        let mut contains = vec![false; self.tets.len()];
        let mut on_boundary = vec![false; self.nodes];
        for (t, tet) in self.tets.iter().enumerate() {
            if tet.iter().any(|&n| index[n as usize] != u32::MAX) {
                contains[t] = true;
                for &n in tet.iter().filter(|&&n| index[n as usize] == u32::MAX) {
                    on_boundary[n as usize] = true;
                }
            }
        }
        let unknowns: Vec<usize> = interior
            .iter()
            .flat_map(|&n| (0..3).filter_map(move |c| self.dofs.get(n, c)))
            .collect();
        let mut local_unknown = vec![u32::MAX; self.dofs.len()];
        for (i, &d) in unknowns.iter().enumerate() {
            local_unknown[d] = i as u32;
        }
        Patch {
            unknowns,
            local_unknown,
            interior,
            index,
            elements: (0..self.tets.len() as u32).filter(|&t| contains[t as usize]).collect(),
            contains,
            boundary: (0..self.nodes as u32).filter(|&n| on_boundary[n as usize]).collect(),
        }
    }

    /// The energy of the patch's elements less the body force's work on its interior: what its
    /// interior DOFs change of the total potential energy.
    fn patch_energy(&self, patch: &Patch, u: &[[f64; 3]], body: f64) -> Option<f64> {
        let mut energy = 0.0;
        for &t in &patch.elements {
            let t = t as usize;
            let law = &self.laws[self.tet_law[t] as usize];
            energy += self.volumes[t] * law.energy(&self.deformation_gradient(t, u))?;
        }
        Some(energy - body * self.work_on(&patch.interior, u))
    }

    /// f_body·u over `nodes`, at full gravity.
    fn work_on(&self, nodes: &[u32], u: &[[f64; 3]]) -> f64 {
        nodes
            .iter()
            .map(|&n| {
                (0..3)
                    .map(|k| self.body_force[n as usize][k] * u[n as usize][k])
                    .sum::<f64>()
            })
            .sum()
    }

    /// The patch's energy, gradient and Hessian over its interior DOFs at `u`, and with `moved`
    /// (a displacement of boundary nodes, indexed like `u`) the coupling −H_IB Δb; `None` if an
    /// element is inverted.
    fn patch_system(
        &self,
        patch: &Patch,
        u: &[[f64; 3]],
        body: f64,
        moved: Option<&[[f64; 3]]>,
        system: &mut LocalSystem,
    ) -> Option<f64> {
        system.hessian.fill(0.0);
        system.gradient.fill(0.0);
        system.coupling.fill(0.0);
        system.magnitude = 0.0;
        let mut energy = 0.0;
        for &t in &patch.elements {
            let t = t as usize;
            let law = &self.laws[self.tet_law[t] as usize];
            let response = law.response(&self.deformation_gradient(t, u))?;
            let (g, v, tet) = (&self.gradients[t], self.volumes[t], self.tets[t]);
            energy += v * response.energy;
            let terms = g.map(|g| response.tangent.node(&g));
            for a in 0..4 {
                let Some(ia) = patch.position(tet[a]) else {
                    continue;
                };
                let force = response.stress * Vector3::from(g[a]);
                for i in 0..3 {
                    system.gradient[3 * ia + i] += v * force[i];
                    system.magnitude += (v * force[i]).abs();
                }
                for b in 0..4 {
                    let block = v * response.tangent.element_block(&terms[a], &terms[b]);
                    match patch.position(tet[b]) {
                        Some(ib) => {
                            for i in 0..3 {
                                for k in 0..3 {
                                    system.hessian[(3 * ia + i, 3 * ib + k)] += block[(i, k)];
                                }
                            }
                        }
                        None => {
                            if let Some(moved) = moved {
                                let step = Vector3::from(moved[tet[b] as usize]);
                                let pushed = block * step;
                                for i in 0..3 {
                                    system.coupling[3 * ia + i] -= pushed[i];
                                }
                            }
                        }
                    }
                }
            }
        }
        for (i, &n) in patch.interior.iter().enumerate() {
            for k in 0..3 {
                system.gradient[3 * i + k] -= body * self.body_force[n as usize][k];
            }
        }
        Some(energy - body * self.work_on(&patch.interior, u))
    }

    /// The largest α before an element of the patch collapses under the node displacement `step`
    /// (indexed like `u`).
    fn patch_feasible_length(&self, patch: &Patch, u: &[[f64; 3]], step: &[[f64; 3]]) -> f64 {
        self.feasible_length_of(patch.elements.iter().map(|&t| t as usize), u, step)
    }

    /// Minimizes the energy over the patch's interior, everything else held, from a feasible `u`,
    /// until its gradient is at most `tolerance` (N) or `reduction` times its first: Newton with the
    /// same feasible, Armijo line search as the global steps. Where Newton stalls, `u` holds the last
    /// accepted state, which has no more energy than the first.
    pub(super) fn relax(
        &self,
        patch: &Patch,
        u: &mut [[f64; 3]],
        body: f64,
        tolerance: f64,
        reduction: f64,
    ) -> Relaxed {
        let mut system = LocalSystem::new(3 * patch.interior.len());
        let mut step = vec![[0.0; 3]; self.nodes];
        let mut base = vec![[0.0; 3]; patch.interior.len()];
        let stalled = |iterations| Relaxed {
            iterations,
            converged: false,
        };
        let mut goal = tolerance;
        for iteration in 0..MAX_LOCAL_ITERATIONS {
            let Some(energy) = self.patch_system(patch, u, body, None, &mut system) else {
                return stalled(iteration);
            };
            let gradient = norm(&system.gradient);
            if iteration == 0 {
                goal = goal.max(reduction * gradient).max(ROUND_OFF * system.magnitude);
            }
            if gradient <= goal {
                return Relaxed {
                    iterations: iteration,
                    converged: true,
                };
            }
            let rhs: Vec<f64> = system.gradient.iter().map(|g| -g).collect();
            let Some(direction) = system.solve(&rhs) else {
                return stalled(iteration);
            };
            for (i, &n) in patch.interior.iter().enumerate() {
                step[n as usize] = [direction[3 * i], direction[3 * i + 1], direction[3 * i + 2]];
                base[i] = u[n as usize];
            }
            let slope: f64 = system.gradient.iter().zip(&direction).map(|(g, d)| g * d).sum();
            let mut length = (FEASIBLE_FRACTION * self.patch_feasible_length(patch, u, &step)).min(1.0);
            let mut accepted = false;
            for _ in 0..20 {
                for (i, &n) in patch.interior.iter().enumerate() {
                    u[n as usize] = std::array::from_fn(|k| base[i][k] + length * step[n as usize][k]);
                }
                if self
                    .patch_energy(patch, u, body)
                    .is_some_and(|e| e <= energy + 1e-4 * length * slope + self.energy_noise)
                {
                    accepted = true;
                    break;
                }
                length /= 2.0;
            }
            if !accepted {
                for (i, &n) in patch.interior.iter().enumerate() {
                    u[n as usize] = base[i];
                }
                return stalled(iteration);
            }
        }
        stalled(MAX_LOCAL_ITERATIONS)
    }

    /// Moves the patch's boundary nodes from where `u` has them to where `goal` has them and solves
    /// the interior on the way: local load steps, each a tangent predictor stopped short of the
    /// first collapse and a relaxation (what the global solver does, on a few hundred unknowns).
    /// `u` must be feasible on the patch; on success its boundary nodes are at `goal`.
    pub(super) fn relax_to(
        &self,
        patch: &Patch,
        u: &mut [[f64; 3]],
        goal: &[[f64; 3]],
        body: f64,
        tolerance: f64,
    ) -> Option<LocalEffort> {
        let mut system = LocalSystem::new(3 * patch.interior.len());
        let start: Vec<[f64; 3]> = patch.boundary.iter().map(|&n| u[n as usize]).collect();
        let mut step = vec![[0.0; 3]; self.nodes];
        let mut trial = u.to_vec();
        let (mut done, mut size, mut cuts) = (0.0f64, 1.0f64, 0);
        let mut effort = LocalEffort::default();
        while done < 1.0 {
            let to = (done + size).min(1.0);
            for (b, &n) in patch.boundary.iter().enumerate() {
                step[n as usize] = std::array::from_fn(|k| (to - done) * (goal[n as usize][k] - start[b][k]));
            }
            for &n in patch.interior.iter().chain(&patch.boundary) {
                trial[n as usize] = u[n as usize];
            }
            let landed = self
                .patch_system(patch, &trial, body, Some(&step), &mut system)
                .and_then(|_| {
                    let rhs: Vec<f64> = system
                        .gradient
                        .iter()
                        .zip(&system.coupling)
                        .map(|(g, c)| c - g)
                        .collect();
                    let predictor = system.solve(&rhs)?;
                    for (i, &n) in patch.interior.iter().enumerate() {
                        step[n as usize] = [predictor[3 * i], predictor[3 * i + 1], predictor[3 * i + 2]];
                    }
                    let fraction = (FEASIBLE_FRACTION * self.patch_feasible_length(patch, &trial, &step)).min(1.0);
                    if fraction < MIN_PREDICTOR_FRACTION {
                        return None;
                    }
                    for &n in patch.interior.iter().chain(&patch.boundary) {
                        trial[n as usize] =
                            std::array::from_fn(|k| trial[n as usize][k] + fraction * step[n as usize][k]);
                    }
                    let reached = done + fraction * (to - done);
                    let last = reached >= 1.0;
                    let goal_tolerance = if last {
                        tolerance
                    } else {
                        LOCAL_INTERMEDIATE * tolerance
                    };
                    let relaxed = self.relax(patch, &mut trial, body, goal_tolerance, LOCAL_REDUCTION);
                    relaxed
                        .converged
                        .then_some((reached, relaxed.iterations, fraction < 1.0))
                });
            match landed {
                Some((reached, iterations, shortened)) => {
                    for &n in patch.interior.iter().chain(&patch.boundary) {
                        u[n as usize] = trial[n as usize];
                    }
                    effort.iterations += iterations + 1;
                    effort.shortened += usize::from(shortened);
                    size = reached - done;
                    done = reached;
                    if iterations <= 4 {
                        size = (1.5 * size).min(1.0);
                    }
                }
                None => {
                    cuts += 1;
                    size /= 2.0;
                    if cuts > MAX_LOCAL_CUTS {
                        return None;
                    }
                }
            }
        }
        // The boundary ends exactly at the goal, not within the round-off of a sum of fractions.
        for &n in &patch.boundary {
            u[n as usize] = goal[n as usize];
        }
        Some(effort)
    }
}

impl Patch {
    /// Puts the patch's nodes, interior and boundary, back where `from` has them.
    pub(super) fn keep(&self, u: &mut [[f64; 3]], from: &[[f64; 3]]) {
        for &n in self.interior.iter().chain(&self.boundary) {
            u[n as usize] = from[n as usize];
        }
    }

    fn local(&self, unknown: usize) -> Option<usize> {
        let i = self.local_unknown[unknown];
        (i != u32::MAX).then_some(i as usize)
    }

    fn position(&self, node: u32) -> Option<usize> {
        let i = self.index[node as usize];
        (i != u32::MAX).then_some(i as usize)
    }
}

impl<'a> PatchBlock<'a> {
    /// The patch's diagonal block of `matrix` (the constrained global tangent), factorized; `None`
    /// where it is not positive definite.
    pub(super) fn new(patch: &'a Patch, matrix: SparseColMatRef<'_, usize, f64>) -> Option<Self> {
        let m = patch.unknowns.len();
        let mut block = Mat::<f64>::zeros(m, m);
        for (j, &column) in patch.unknowns.iter().enumerate() {
            for (row, value) in column_of(matrix, column) {
                if let Some(i) = patch.local(row) {
                    block[(i, j)] = value;
                }
            }
        }
        let block = block.llt(Side::Lower).ok()?;
        Some(Self { patch, block })
    }

    /// z ← M⁻¹ z for the symmetric multiplicative Schwarz preconditioner of `matrix` (K) built
    /// from the patch's exact block B and `factor` (F, an earlier tangent's): y = B⁻¹r on the
    /// patch, then y += F⁻¹(r − Ky), then y += B⁻¹(r − Ky) on the patch. The old factor stands for
    /// the organ, where the tangent changes slowly; the block for the graspers' neighbourhood, where
    /// the elimination moves the state most between corrections.
    pub(super) fn precondition(&self, matrix: SparseColMatRef<'_, usize, f64>, factor: &mut dyn Factor, z: &mut [f64]) {
        let unknowns = &self.patch.unknowns;
        let r = z.to_vec();
        let mut local: Vec<f64> = unknowns.iter().map(|&d| r[d]).collect();
        self.solve_block(&mut local);
        // t = r − K y, with y zero off the patch: only the patch's columns of K contribute.
        let mut t = r.clone();
        for (&column, &y) in unknowns.iter().zip(&local) {
            for (row, value) in column_of(matrix, column) {
                t[row] -= value * y;
            }
        }
        factor.solve_in_place(&mut t);
        for (&d, &y) in unknowns.iter().zip(&local) {
            t[d] += y;
        }
        // (r − K y) on the patch's rows: K is symmetric, so a row is its column.
        let mut residual: Vec<f64> = unknowns
            .iter()
            .map(|&d| r[d] - column_of(matrix, d).map(|(row, value)| value * t[row]).sum::<f64>())
            .collect();
        self.solve_block(&mut residual);
        for (&d, &y) in unknowns.iter().zip(&residual) {
            t[d] += y;
        }
        z.copy_from_slice(&t);
    }

    fn solve_block(&self, x: &mut [f64]) {
        let mut column = Mat::<f64>::from_fn(x.len(), 1, |i, _| x[i]);
        self.block.solve_in_place(column.as_mut());
        for (i, v) in x.iter_mut().enumerate() {
            *v = column[(i, 0)];
        }
    }
}

/// The (row, value) entries of one column of a CSC matrix.
fn column_of<'m>(matrix: SparseColMatRef<'m, usize, f64>, column: usize) -> impl Iterator<Item = (usize, f64)> + 'm {
    let range = matrix.col_ptr()[column]..matrix.col_ptr()[column + 1];
    matrix.row_idx()[range.clone()]
        .iter()
        .copied()
        .zip(matrix.val()[range].iter().copied())
}
