//! Linear finite elements against exact solutions, and green-linear against the direct solve.

mod common;

use std::path::Path;

use common::msh_fixture::Fixture;
use nak::fem::linear::{DofMap, assemble, element_stiffness, shape_gradients};
use nak::fem::{GreenFunctions, LinearSystem, Stiffness, solve_dirichlet};
use nak::mesh::{self, MeshConfig, MeshSource, TetMesh};
use nak::prior::InteractionPoints;

fn config(nu: f64) -> MeshConfig {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/model.toml");
    let mut c = MeshConfig::parse(&std::fs::read_to_string(path).unwrap(), "model.toml").unwrap();
    for m in c.materials.values_mut() {
        m.poisson_ratio = nu;
    }
    c
}

fn fixture_mesh(f: &Fixture, nu: f64) -> TetMesh {
    TetMesh::from_msh(f.to_msh().as_bytes(), "fixture.msh", config(nu)).unwrap()
}

/// y = K x for a faer CSC matrix.
fn matvec(k: &faer::sparse::SparseColMat<usize, f64>, x: &[f64]) -> Vec<f64> {
    let mut y = vec![0.0; k.nrows()];
    let (col_ptr, rows, vals) = (k.symbolic().col_ptr(), k.symbolic().row_idx(), k.val());
    for j in 0..k.ncols() {
        for p in col_ptr[j]..col_ptr[j + 1] {
            y[rows[p]] += vals[p] * x[j];
        }
    }
    y
}

#[test]
fn element_stiffness_is_symmetric_and_annihilates_rigid_motions() {
    let p = [
        [0.0, 0.0, 0.0],
        [0.02, 0.001, 0.0],
        [0.003, 0.015, 0.002],
        [0.001, 0.004, 0.018],
    ];
    let (g, v) = shape_gradients(p).unwrap();
    let k = element_stiffness(&g, v, 1000.0, 700.0);
    for (i, row) in k.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            assert!((v - k[j][i]).abs() <= 1e-12 * row[i].abs());
        }
    }
    // Translations and infinitesimal rotations ω × x produce no force.
    let mut modes: Vec<[f64; 12]> = (0..3)
        .map(|c| std::array::from_fn(|d| if d % 3 == c { 1.0 } else { 0.0 }))
        .collect();
    for w in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]] {
        modes.push(std::array::from_fn(|d| {
            let x = p[d / 3];
            let r = [
                w[1] * x[2] - w[2] * x[1],
                w[2] * x[0] - w[0] * x[2],
                w[0] * x[1] - w[1] * x[0],
            ];
            r[d % 3]
        }));
    }
    let scale = k.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    for mode in modes {
        for row in &k {
            let f: f64 = row.iter().zip(&mode).map(|(a, b)| a * b).sum();
            assert!(f.abs() < 1e-12 * scale * 0.02, "{f}");
        }
    }
}

#[test]
fn assembled_stiffness_is_symmetric_positive_definite_once_fixed() {
    let m = fixture_mesh(&Fixture::grid(3), 0.45);
    let all = DofMap::without(m.node_count(), &[]);
    let k = assemble(&m, &all).unwrap().stiffness;
    // Symmetric: K = Kᵀ through products with unit vectors of a few columns.
    for j in [0, 7, 40, 100] {
        let e: Vec<f64> = (0..k.ncols()).map(|i| if i == j { 1.0 } else { 0.0 }).collect();
        let col = matvec(&k, &e);
        for (i, v) in col.iter().enumerate() {
            let ei: Vec<f64> = (0..k.ncols()).map(|r| if r == i { 1.0 } else { 0.0 }).collect();
            assert!((matvec(&k, &ei)[j] - v).abs() < 1e-9);
        }
    }
    // Free: rigid motions are in the kernel. Fixed: Cholesky succeeds (positive definite).
    let rotation: Vec<f64> = m.positions.iter().flat_map(|p| [-p[1], p[0], 0.0]).collect();
    let force = matvec(&k, &rotation);
    assert!(force.iter().all(|f| f.abs() < 1e-9), "rotation produces force");
    assert!(LinearSystem::new(&m).is_ok());
}

#[test]
fn patch_test_reproduces_a_linear_field_exactly() {
    // u = c x vanishes on the fixed face x = 0; prescribe it on every other surface node.
    let m = fixture_mesh(&Fixture::grid(3), 0.45);
    let c = [0.02, -0.01, 0.015];
    let exact = |p: [f64; 3]| c.map(|ci| ci * p[0]);
    let prescribed: Vec<(u32, [f64; 3])> = m
        .surface_nodes
        .iter()
        .filter(|&&n| m.positions[n as usize][0] > 0.0)
        .map(|&n| (n, exact(m.positions[n as usize])))
        .collect();
    let u = solve_dirichlet(&m, &prescribed).unwrap();
    let interior: Vec<usize> = (0..m.node_count()).filter(|&n| !m.is_surface[n]).collect();
    assert_eq!(interior.len(), 8);
    for n in interior {
        let want = exact(m.positions[n]);
        for k in 0..3 {
            assert!((u[n][k] - want[k]).abs() < 1e-12, "node {n}: {:?} vs {want:?}", u[n]);
        }
    }
}

/// Tip deflection of a cantilever (fixed at x = 0) under a transverse tip load, against
/// Euler–Bernoulli + Timoshenko shear: δ = F L³/(3EI) + F L/(κ G A).
fn cantilever_error(cells_across: usize) -> f64 {
    let (length, side) = (0.1, 0.01);
    let n = cells_across;
    let f = Fixture::bar(
        [10 * n, n, n],
        [length / (10 * n) as f64, side / n as f64, side / n as f64],
    );
    let m = fixture_mesh(&f, 0.0);
    let mu = m.config.materials["liver"].shear_modulus;
    let young = 2.0 * mu;
    let system = LinearSystem::new(&m).unwrap();
    let tip: Vec<u32> = m.node_sets["grasp_01"].clone();
    let load = 1e-4; // N in −y, spread evenly over the tip face's nodes
    let mut rhs = faer::Mat::<f64>::zeros(system.dofs.len(), 1);
    for &t in &tip {
        rhs[(system.dofs.get(t, 1).unwrap(), 0)] = -load / tip.len() as f64;
    }
    system.solve_in_place(&mut rhs);
    let deflection = -tip
        .iter()
        .map(|&t| rhs[(system.dofs.get(t, 1).unwrap(), 0)])
        .sum::<f64>()
        / tip.len() as f64;
    let inertia = side.powi(4) / 12.0;
    let exact = load * length.powi(3) / (3.0 * young * inertia) + load * length / (5.0 / 6.0 * mu * side * side);
    (deflection - exact).abs() / exact
}

#[test]
fn a_cantilever_converges_to_beam_theory_under_refinement() {
    let errors: Vec<f64> = [1, 2, 4].into_iter().map(cantilever_error).collect();
    // Linear tetrahedra lock in bending: coarse meshes are far too stiff (76 % at one cell across,
    // 45 % at two, 18 % at four when written), and refinement must close the gap at a rate
    // approaching the O(h²) of P1 displacements.
    assert!(errors[0] > errors[1] && errors[1] > errors[2], "{errors:?}");
    assert!(errors[2] < 0.2, "{errors:?}");
    assert!(errors[1] / errors[2] > 2.0, "rate too low: {errors:?}");
}

#[test]
fn green_linear_equals_a_direct_solve_moves_grasped_nodes_exactly_and_gives_its_forces() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver/liver-coarse.msh");
    let m = mesh::load(&MeshSource::File(path)).unwrap();
    let cache = tempfile::tempdir().unwrap();
    let green = GreenFunctions::load_or_compute(&m, Stiffness::Linear, cache.path(), |_, _| {}).unwrap();
    let mut points = InteractionPoints::default();
    for (set, u) in [("grasp_03", [0.01, 0.03, -0.01]), ("grasp_08", [-0.02, 0.02, 0.015])] {
        for &n in m.node_sets[set].iter().take(6) {
            points.push(n, m.positions[n as usize], u);
        }
    }
    let mut served = vec![0.0f32; 3 * m.node_count()];
    let mut forces = Vec::new();
    green
        .solve(&points.nodes, &points.displacements, None, &mut served, &mut forces)
        .unwrap();
    let prescribed: Vec<(u32, [f64; 3])> = points
        .nodes
        .iter()
        .copied()
        .zip(points.displacements.iter().copied())
        .collect();
    let direct = solve_dirichlet(&m, &prescribed).unwrap();
    let diff: f64 = served
        .chunks(3)
        .zip(&direct)
        .map(|(a, b)| (0..3).map(|k| (a[k] as f64 - b[k]).powi(2)).sum::<f64>())
        .sum();
    let norm: f64 = direct.iter().map(|b| b.iter().map(|v| v * v).sum::<f64>()).sum();
    let relative = (diff / norm).sqrt();
    assert!(relative < 1e-6, "relative difference {relative:e}");
    for (n, u) in &prescribed {
        for k in 0..3 {
            assert!(
                (served[3 * *n as usize + k] as f64 - u[k]).abs() < 1e-7,
                "grasped node {n}"
            );
        }
    }
    // The capacitance forces (G[S,S])⁻¹ u_S are K·u of the direct solve at the held nodes. G is
    // cached in f32, so they agree to about f32 precision times G[S,S]'s conditioning.
    let reference = nak::fem::nodal_forces(&m, &direct, &points.nodes).unwrap();
    let scale = reference.iter().flatten().map(|f| f * f).sum::<f64>().sqrt();
    let error = forces
        .iter()
        .flatten()
        .zip(reference.iter().flatten())
        .map(|(a, b)| (a - b).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!(error / scale < 1e-6, "forces differ by {:e} relative", error / scale);
    // K·u itself: free nodes carry no force, and the held and fixed nodes' forces balance.
    let everything: Vec<u32> = (0..m.node_count() as u32).collect();
    let all = nak::fem::nodal_forces(&m, &direct, &everything).unwrap();
    let held: std::collections::HashSet<u32> = points
        .nodes
        .iter()
        .copied()
        .chain(m.node_sets["fixed"].iter().copied())
        .collect();
    let free_largest = (0..m.node_count())
        .filter(|n| !held.contains(&(*n as u32)))
        .map(|n| all[n].iter().map(|f| f * f).sum::<f64>().sqrt())
        .fold(0.0, f64::max);
    assert!(free_largest < 1e-9 * scale, "a free node carries {free_largest:e} N");
    let total: Vec<f64> = (0..3).map(|k| all.iter().map(|f| f[k]).sum::<f64>()).collect();
    assert!(
        total.iter().all(|t| t.abs() < 1e-9 * scale),
        "K·u does not balance: {total:?}"
    );
    // A second load reads the cache instead of recomputing.
    let again =
        GreenFunctions::load_or_compute(&m, Stiffness::Linear, cache.path(), |_, _| panic!("recomputed")).unwrap();
    assert_eq!(again.candidates(), green.candidates());
}
