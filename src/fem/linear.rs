//! Small-strain isotropic linear elasticity on P1 tetrahedra (docs/design.md §4): sparse assembly with
//! faer, `fixed` nodes eliminated, sparse Cholesky factorized once and reused.

use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::Llt;
use faer::sparse::{SparseColMat, Triplet};
use faer::{Mat, Side};

use super::FemError;
use crate::mesh::TetMesh;
use crate::mesh::topology::Vec3;

/// Lamé's first parameter from the shear modulus and Poisson's ratio.
pub fn lame_lambda(mu: f64, nu: f64) -> f64 {
    2.0 * mu * nu / (1.0 - 2.0 * nu)
}

/// Gradients of the four linear shape functions of a tetrahedron, and its volume.
pub fn shape_gradients(p: [Vec3; 4]) -> Option<([Vec3; 4], f64)> {
    let e = |i: usize| [p[i][0] - p[0][0], p[i][1] - p[0][1], p[i][2] - p[0][2]];
    let j = nalgebra::Matrix3::new(
        e(1)[0],
        e(2)[0],
        e(3)[0], //
        e(1)[1],
        e(2)[1],
        e(3)[1], //
        e(1)[2],
        e(2)[2],
        e(3)[2],
    );
    let det = j.determinant();
    let inv = j.try_inverse()?;
    // ∇N_1..3 are the rows of J⁻¹; ∇N_0 = −(∇N_1 + ∇N_2 + ∇N_3).
    let row = |r: usize| [inv[(r, 0)], inv[(r, 1)], inv[(r, 2)]];
    let (g1, g2, g3) = (row(0), row(1), row(2));
    let g0 = [
        -(g1[0] + g2[0] + g3[0]),
        -(g1[1] + g2[1] + g3[1]),
        -(g1[2] + g2[2] + g3[2]),
    ];
    Some(([g0, g1, g2, g3], det / 6.0))
}

/// The 12×12 element stiffness, DOF order (node a, component i) → 3a + i:
/// `K[3a+i][3b+j] = V (λ ∂_i N_a ∂_j N_b + μ (∂_j N_a ∂_i N_b + δ_ij ∇N_a·∇N_b))`.
pub fn element_stiffness(grads: &[Vec3; 4], volume: f64, lambda: f64, mu: f64) -> [[f64; 12]; 12] {
    let mut k = [[0.0; 12]; 12];
    for a in 0..4 {
        for b in 0..4 {
            let dot = (0..3).map(|c| grads[a][c] * grads[b][c]).sum::<f64>();
            for i in 0..3 {
                for j in 0..3 {
                    let shear = mu * (grads[a][j] * grads[b][i] + if i == j { dot } else { 0.0 });
                    k[3 * a + i][3 * b + j] = volume * (lambda * grads[a][i] * grads[b][j] + shear);
                }
            }
        }
    }
    k
}

/// Which DOFs are unknowns: every component of every node not in `fixed` (and not prescribed).
#[derive(Debug, Clone, PartialEq)]
pub struct DofMap {
    /// Unknown index per (node, component), `None` for constrained ones.
    index: Vec<Option<u32>>,
    count: usize,
}

impl DofMap {
    /// All DOFs except those of `constrained` nodes, numbered by node.
    pub fn without(node_count: usize, constrained: &[u32]) -> Self {
        let mut free = vec![true; node_count];
        for &n in constrained {
            free[n as usize] = false;
        }
        let order: Vec<u32> = (0..node_count as u32).filter(|&n| free[n as usize]).collect();
        Self::in_order(node_count, &order)
    }

    /// The DOFs of the nodes in `order`, numbered in that order; every other node is constrained.
    pub fn in_order(node_count: usize, order: &[u32]) -> Self {
        let mut index = vec![None; 3 * node_count];
        for (rank, &n) in order.iter().enumerate() {
            for c in 0..3 {
                index[3 * n as usize + c] = Some((3 * rank + c) as u32);
            }
        }
        Self {
            index,
            count: 3 * order.len(),
        }
    }

    pub fn len(&self) -> usize {
        self.count
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    pub fn get(&self, node: u32, component: usize) -> Option<usize> {
        self.index[3 * node as usize + component].map(|i| i as usize)
    }
}

/// Per-tetrahedron Lamé parameters from the mesh's region materials.
fn lame_per_tet(mesh: &TetMesh) -> Result<Vec<(f64, f64)>, FemError> {
    let per_region: Vec<(f64, f64)> = super::region_materials(mesh)?
        .into_iter()
        .map(|m| (lame_lambda(m.shear_modulus, m.poisson_ratio), m.shear_modulus))
        .collect();
    Ok(mesh.tet_region.iter().map(|&r| per_region[r as usize]).collect())
}

/// One stiffness entry coupling a free row to a constrained DOF: (free row, node, component, value).
pub type Coupling = (usize, u32, usize, f64);

/// The stiffness restricted to `dofs` (rows and columns), and the coupling to constrained DOFs for
/// building right-hand sides.
pub struct Assembled {
    pub stiffness: SparseColMat<usize, f64>,
    pub coupling: Vec<Coupling>,
}

pub fn assemble(mesh: &TetMesh, dofs: &DofMap) -> Result<Assembled, FemError> {
    let lame = lame_per_tet(mesh)?;
    let mut triplets = Vec::with_capacity(mesh.tets.len() * 144);
    let mut coupling = Vec::new();
    for (t, tet) in mesh.tets.iter().enumerate() {
        let p = tet.map(|n| mesh.positions[n as usize]);
        let (grads, volume) = shape_gradients(p).ok_or(FemError::Degenerate(t))?;
        let (lambda, mu) = lame[t];
        let k = element_stiffness(&grads, volume, lambda, mu);
        for a in 0..4 {
            for i in 0..3 {
                let Some(row) = dofs.get(tet[a], i) else { continue };
                for b in 0..4 {
                    for j in 0..3 {
                        let value = k[3 * a + i][3 * b + j];
                        match dofs.get(tet[b], j) {
                            Some(col) => triplets.push(Triplet::new(row, col, value)),
                            None => coupling.push((row, tet[b], j, value)),
                        }
                    }
                }
            }
        }
    }
    let n = dofs.len();
    let stiffness =
        SparseColMat::try_new_from_triplets(n, n, &triplets).map_err(|e| FemError::Assembly(format!("{e:?}")))?;
    Ok(Assembled { stiffness, coupling })
}

/// A factorized stiffness on the DOFs of every node that is not `fixed`.
pub struct LinearSystem {
    pub dofs: DofMap,
    factor: Llt<usize, f64>,
}

impl LinearSystem {
    /// Assembles and factorizes the stiffness with the `fixed` node set eliminated.
    pub fn new(mesh: &TetMesh) -> Result<Self, FemError> {
        let fixed = mesh.node_sets.get("fixed").cloned().unwrap_or_default();
        Self::with_constrained(mesh, &fixed).map(|(s, _)| s)
    }

    /// Eliminates `constrained` nodes; returns the system and the coupling to them.
    pub fn with_constrained(mesh: &TetMesh, constrained: &[u32]) -> Result<(Self, Vec<Coupling>), FemError> {
        let dofs = DofMap::without(mesh.node_count(), constrained);
        let assembled = assemble(mesh, &dofs)?;
        Ok((Self::from_stiffness(dofs, &assembled.stiffness)?, assembled.coupling))
    }

    /// Factorizes a symmetric positive definite `stiffness` (its lower triangle is read) on the
    /// unknowns `dofs` numbers.
    pub fn from_stiffness(dofs: DofMap, stiffness: &SparseColMat<usize, f64>) -> Result<Self, FemError> {
        let factor = stiffness
            .sp_cholesky(Side::Lower)
            .map_err(|e| FemError::NotPositiveDefinite(format!("{e:?}")))?;
        Ok(Self { dofs, factor })
    }

    /// Solves K x = b in place; `b` has one column per right-hand side.
    pub fn solve_in_place(&self, b: &mut Mat<f64>) {
        self.factor.solve_in_place(b.as_mut());
    }
}

/// The elastic force `K·u` (N) at each of `nodes`, summed element by element. At the held nodes of
/// a Dirichlet solution it is the force that holds them there (nothing else loads a linear body).
pub fn nodal_forces(mesh: &TetMesh, u: &[[f64; 3]], nodes: &[u32]) -> Result<Vec<[f64; 3]>, FemError> {
    let lame = lame_per_tet(mesh)?;
    let mut slot = vec![None; mesh.node_count()];
    for (i, &n) in nodes.iter().enumerate() {
        slot[n as usize] = Some(i);
    }
    let mut forces = vec![[0.0; 3]; nodes.len()];
    for (t, tet) in mesh.tets.iter().enumerate() {
        if tet.iter().all(|&n| slot[n as usize].is_none()) {
            continue;
        }
        let (grads, volume) =
            shape_gradients(tet.map(|n| mesh.positions[n as usize])).ok_or(FemError::Degenerate(t))?;
        let k = element_stiffness(&grads, volume, lame[t].0, lame[t].1);
        for (a, &node) in tet.iter().enumerate() {
            let Some(i) = slot[node as usize] else { continue };
            for (c, f) in forces[i].iter_mut().enumerate() {
                *f += (0..12)
                    .map(|d| k[3 * a + c][d] * u[tet[d / 3] as usize][d % 3])
                    .sum::<f64>();
            }
        }
    }
    Ok(forces)
}

/// The displacement of every node with `prescribed` nodes moved as given and `fixed` nodes held:
/// the reference direct solve (one factorization per call).
pub fn solve_dirichlet(mesh: &TetMesh, prescribed: &[(u32, [f64; 3])]) -> Result<Vec<[f64; 3]>, FemError> {
    let mut constrained = mesh.node_sets.get("fixed").cloned().unwrap_or_default();
    constrained.extend(prescribed.iter().map(|(n, _)| *n));
    let (system, coupling) = LinearSystem::with_constrained(mesh, &constrained)?;
    let mut value = vec![None; mesh.node_count()];
    for &(n, u) in prescribed {
        value[n as usize] = Some(u);
    }
    let mut rhs = Mat::<f64>::zeros(system.dofs.len(), 1);
    for (row, node, component, k) in coupling {
        if let Some(u) = value[node as usize] {
            rhs[(row, 0)] -= k * u[component];
        }
    }
    system.solve_in_place(&mut rhs);
    Ok((0..mesh.node_count() as u32)
        .map(|n| match value[n as usize] {
            Some(u) => u,
            None => std::array::from_fn(|c| system.dofs.get(n, c).map_or(0.0, |i| rhs[(i, 0)])),
        })
        .collect())
}
