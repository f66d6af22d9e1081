//! The Kelvinlet prior against its defining properties and an independent f64 implementation.

use std::path::Path;

use nak::mesh::{self, MeshSource, PriorParams, TetMesh};
use nak::prior::{InteractionPoints, Kelvinlet, NodeCloud, Workspace};
use nalgebra::{DMatrix, DVector, Matrix3, Vector3};

fn coarse() -> TetMesh {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver/liver-coarse.msh");
    mesh::load(&MeshSource::File(path)).unwrap()
}

/// docs/design.md §3 written out directly in f64: the bracket, the normal equations, the sum.
fn reference_field(params: PriorParams, points: &InteractionPoints, at: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let (nu, eps, lambda) = (params.poisson_ratio, params.epsilon, params.lambda);
    let gamma = |x: Vector3<f64>, xs: Vector3<f64>| -> Matrix3<f64> {
        let r = x - xs;
        let re = (r.norm_squared() + eps * eps).sqrt();
        let bracket = Matrix3::identity() * ((3.0 - 4.0 * nu) / re + 2.0 * (1.0 - nu) * eps * eps / re.powi(3))
            + r * r.transpose() / re.powi(3);
        bracket * (eps / (5.0 - 6.0 * nu))
    };
    let xs: Vec<Vector3<f64>> = points.positions.iter().map(|p| Vector3::from(*p)).collect();
    let k = xs.len();
    let coefficients: Vec<Vector3<f64>> = if k == 1 {
        vec![Vector3::from(points.displacements[0])]
    } else {
        let mut g = DMatrix::zeros(3 * k, 3 * k);
        for i in 0..k {
            for j in 0..k {
                g.view_mut((3 * i, 3 * j), (3, 3)).copy_from(&gamma(xs[i], xs[j]));
            }
        }
        let u = DVector::from_iterator(3 * k, points.displacements.iter().flatten().copied());
        let lhs = g.transpose() * &g + DMatrix::identity(3 * k, 3 * k) * lambda;
        let sol = lhs.lu().solve(&(g.transpose() * u)).unwrap();
        (0..k)
            .map(|j| Vector3::new(sol[3 * j], sol[3 * j + 1], sol[3 * j + 2]))
            .collect()
    };
    at.iter()
        .map(|p| {
            let x = Vector3::from(*p);
            let u: Vector3<f64> = xs.iter().zip(&coefficients).map(|(xj, kj)| gamma(x, *xj) * kj).sum();
            [u.x, u.y, u.z]
        })
        .collect()
}

fn field(prior: &Kelvinlet, points: &InteractionPoints, at: &[[f64; 3]]) -> Vec<f32> {
    let cloud = NodeCloud::new(at.iter().copied());
    let mut ws = Workspace::default();
    prior.solve(points, &mut ws).unwrap();
    let mut out = vec![0.0f32; 3 * at.len()];
    prior.evaluate(&ws.coefficients, &cloud, &mut out);
    out
}

/// Two graspers of ten nodes each from grasp regions 2 and 7, moved by different displacements.
fn two_graspers(m: &TetMesh) -> InteractionPoints {
    let mut points = InteractionPoints::default();
    for (set, u) in [("grasp_02", [0.01, 0.03, -0.005]), ("grasp_07", [-0.02, 0.015, 0.02])] {
        for &n in m.node_sets[set].iter().take(10) {
            points.push(n, m.positions[n as usize], u);
        }
    }
    points
}

fn relative_error(a: &[f32], b: &[[f64; 3]]) -> f64 {
    let diff: f64 = a
        .chunks(3)
        .zip(b)
        .map(|(x, y)| (0..3).map(|k| (x[k] as f64 - y[k]).powi(2)).sum::<f64>())
        .sum();
    let norm: f64 = b.iter().map(|y| y.iter().map(|v| v * v).sum::<f64>()).sum();
    (diff / norm).sqrt()
}

#[test]
fn a_single_point_moves_by_exactly_its_displacement() {
    let m = coarse();
    let prior = Kelvinlet::new(m.config.prior);
    let node = m.node_sets["grasp_05"][0];
    let mut points = InteractionPoints::default();
    points.push(node, m.positions[node as usize], [0.012, -0.034, 0.05]);
    let u = field(&prior, &points, &m.positions);
    let at = &u[3 * node as usize..3 * node as usize + 3];
    for (got, want) in at.iter().zip([0.012, -0.034, 0.05]) {
        assert!((*got as f64 - want).abs() <= 1e-6 * 0.05, "{got} vs {want}");
    }
}

#[test]
fn the_bracket_is_the_identity_at_its_centre_and_decays() {
    let prior = Kelvinlet::new(PriorParams::default());
    let at_centre = prior.response([0.0; 3]);
    for (i, row) in at_centre.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            assert!((v - if i == j { 1.0 } else { 0.0 }).abs() < 1e-15);
        }
    }
    let far = prior.response([0.5, 0.0, 0.0]);
    assert!(far[0][0] < 0.2 && far[1][1] < far[0][0]);
}

#[test]
fn agrees_with_a_straightforward_f64_implementation() {
    let m = coarse();
    let params = m.config.prior;
    let prior = Kelvinlet::new(params);
    let points = two_graspers(&m);
    let got = field(&prior, &points, &m.positions);
    let want = reference_field(params, &points, &m.positions);
    let err = relative_error(&got, &want);
    assert!(err < 1e-5, "relative error {err:e}");
    // And with a single point, the direct formula.
    let mut one = InteractionPoints::default();
    one.push(points.nodes[0], points.positions[0], points.displacements[0]);
    let err = relative_error(
        &field(&prior, &one, &m.positions),
        &reference_field(params, &one, &m.positions),
    );
    assert!(err < 1e-5, "relative error {err:e}");
}

#[test]
fn many_points_and_meshes_that_are_not_whole_blocks() {
    let m = coarse();
    let prior = Kelvinlet::new(m.config.prior);
    let mut points = InteractionPoints::default();
    for (i, &n) in m.surface_nodes.iter().step_by(17).take(64).enumerate() {
        let t = i as f64;
        points.push(n, m.positions[n as usize], [0.01 * t.sin(), 0.01 * t.cos(), 0.005]);
    }
    // 1,000 nodes: not a multiple of the block size, below the parallel threshold.
    let at: Vec<[f64; 3]> = m.positions[..1000].to_vec();
    let err = relative_error(
        &field(&prior, &points, &at),
        &reference_field(m.config.prior, &points, &at),
    );
    assert!(err < 1e-5, "relative error {err:e}");
}

#[test]
fn the_field_is_linear_in_the_displacements() {
    let m = coarse();
    let prior = Kelvinlet::new(m.config.prior);
    let a = two_graspers(&m);
    let mut b = a.clone();
    for (i, d) in b.displacements.iter_mut().enumerate() {
        *d = [0.002 * i as f64, -0.01, 0.004];
    }
    let mut sum = a.clone();
    for (s, d) in sum.displacements.iter_mut().zip(&b.displacements) {
        *s = std::array::from_fn(|k| s[k] + d[k]);
    }
    let (ua, ub, us) = (
        field(&prior, &a, &m.positions),
        field(&prior, &b, &m.positions),
        field(&prior, &sum, &m.positions),
    );
    let scale = us.iter().fold(0.0f32, |acc, v| acc.max(v.abs()));
    for i in 0..us.len() {
        assert!((ua[i] + ub[i] - us[i]).abs() <= 1e-5 * scale, "component {i}");
    }
}

#[test]
fn the_field_moves_with_rigid_motions_of_the_scene() {
    let m = coarse();
    let params = m.config.prior;
    let prior = Kelvinlet::new(params);
    let points = two_graspers(&m);
    let base = field(&prior, &points, &m.positions);
    // Rotate 90° about z and translate everything: positions, grasp points and displacements.
    let rotate = |p: [f64; 3]| [-p[1], p[0], p[2]];
    let moved = |p: [f64; 3]| {
        let r = rotate(p);
        [r[0] + 0.03, r[1] - 0.02, r[2] + 0.01]
    };
    let mut turned = points.clone();
    for (p, d) in turned.positions.iter_mut().zip(turned.displacements.iter_mut()) {
        *p = moved(*p);
        *d = rotate(*d);
    }
    let at: Vec<[f64; 3]> = m.positions.iter().map(|p| moved(*p)).collect();
    let got = field(&prior, &turned, &at);
    let scale = base.iter().fold(0.0f32, |acc, v| acc.max(v.abs()));
    for (g, b) in got.chunks(3).zip(base.chunks(3)) {
        let want = rotate([b[0] as f64, b[1] as f64, b[2] as f64]);
        for k in 0..3 {
            assert!(
                (g[k] as f64 - want[k]).abs() <= 1e-5 * scale as f64,
                "{g:?} vs {want:?}"
            );
        }
    }
}

#[test]
fn the_interaction_matrix_is_symmetric() {
    // Γ_j(x_i) = Γ_i(x_j): the response depends on r only through |r| and r rᵀ.
    let prior = Kelvinlet::new(PriorParams::default());
    let r = [0.013, -0.021, 0.007];
    assert_eq!(prior.response(r), prior.response(r.map(|v| -v)));
    let m = prior.response(r);
    let transposed: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| m[j][i]));
    assert_eq!(m, transposed);
}

#[test]
fn several_points_approximately_reproduce_their_displacements() {
    let m = coarse();
    let prior = Kelvinlet::new(m.config.prior);
    let points = two_graspers(&m);
    let u = field(&prior, &points, &m.positions);
    // λ = 1e-3 trades exact interpolation for conditioning; the fit stays within a few percent.
    for (n, d) in points.nodes.iter().zip(&points.displacements) {
        let got = &u[3 * *n as usize..3 * *n as usize + 3];
        let err = (0..3).map(|k| (got[k] as f64 - d[k]).powi(2)).sum::<f64>().sqrt();
        let size = d.iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!(err < 0.05 * size, "node {n}: {got:?} vs {d:?}");
    }
}

#[test]
fn the_phantom_field_is_identical_serially_and_in_parallel() {
    // The fine phantom crosses the parallel threshold; the coarse one does not. On a pool thread (as
    // `nak serve` computes pooled requests) its blocks are spread over the pool; from any other
    // thread (quick requests, on the connection's thread) it is computed there alone. The per-node
    // arithmetic must not depend on either.
    let fine = mesh::load(&MeshSource::Embedded).unwrap();
    let prior = Kelvinlet::new(fine.config.prior);
    let points = two_graspers(&fine);
    let alone = field(&prior, &points, &fine.positions);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(4).build().unwrap();
    let spread = pool.install(|| field(&prior, &points, &fine.positions));
    assert_eq!(alone, spread);
}

/// Kelvin's singular solution: displacement at offset `r` from a point load `f` in an infinite
/// medium, `u = [(3−4ν) f + r̂ (r̂·f)] / (16πμ(1−ν)|r|)`.
fn kelvin(mu: f64, nu: f64, r: Vector3<f64>, f: Vector3<f64>) -> Vector3<f64> {
    let d = r.norm();
    let hat = r / d;
    ((3.0 - 4.0 * nu) * f + hat * hat.dot(&f)) / (16.0 * std::f64::consts::PI * mu * (1.0 - nu) * d)
}

#[test]
fn the_kelvinlet_force_is_the_point_load_whose_far_field_is_kelvins_solution() {
    use nak::engine::{Engine, Forces, Grasp, Limits, Request};
    let m = std::sync::Arc::new(coarse());
    let engine = Engine::new(m.clone(), Limits::default());
    let kelvinlet = engine.models().find(|i| i.name == "kelvinlet").unwrap();
    assert_eq!(kelvinlet.forces, Forces::Estimate);
    // A node inside the liver region, so that μ is the liver's.
    let liver = m.regions.iter().position(|r| r.name == "liver").unwrap() as u16;
    let node = m.node_sets["grasp_05"]
        .iter()
        .copied()
        .find(|&n| m.node_region[n as usize] == Some(liver))
        .unwrap();
    let u = [0.01, -0.02, 0.015];
    let grasp = |nodes: Vec<u32>, displacement| Grasp {
        nodes,
        displacement,
        ..Grasp::default()
    };
    let request = Request {
        grasps: vec![grasp(vec![node], u)],
        ..Request::default()
    };
    let answer = engine.predict(&request).unwrap();
    let f = Vector3::from(answer.grasp_forces.unwrap()[0]);
    let prior = Kelvinlet::new(m.config.prior);
    let (mu, nu) = (m.config.materials["liver"].shear_modulus, m.config.prior.poisson_ratio);
    // Far from the load (|r| = 40 ε) the regularized field is Kelvin's to O(ε²/|r|²) = 6e-4.
    for direction in [Vector3::x(), Vector3::new(0.3, -1.0, 0.5).normalize()] {
        let r = direction * 40.0 * m.config.prior.epsilon;
        let response = Matrix3::from_fn(|i, j| prior.response([r.x, r.y, r.z])[i][j]);
        let regularized = response * Vector3::from(u);
        let singular = kelvin(mu, nu, r, f);
        let relative = (regularized - singular).norm() / singular.norm();
        assert!(
            relative < 1e-3,
            "at {r:?}: Kelvinlet {regularized:?}, Kelvin {singular:?}"
        );
    }
    // A grasp of several points: far away its field is that of their total load (to the cluster's
    // size over the distance, 1 %), and that total is what the grasp reports.
    let held: Vec<u32> = m.node_sets["grasp_05"]
        .iter()
        .copied()
        .filter(|&n| m.node_region[n as usize] == Some(liver))
        .take(6)
        .collect();
    let request = Request {
        grasps: vec![grasp(held.clone(), u)],
        ..Request::default()
    };
    let total = Vector3::from(engine.predict(&request).unwrap().grasp_forces.unwrap()[0]);
    let mut points = InteractionPoints::default();
    for &n in &held {
        points.push(n, m.positions[n as usize], u);
    }
    let centre: Vector3<f64> = held
        .iter()
        .map(|&n| Vector3::from(m.positions[n as usize]))
        .sum::<Vector3<f64>>()
        / 6.0;
    let r = Vector3::new(-0.2, 1.0, 0.4).normalize() * 40.0 * m.config.prior.epsilon;
    let far = centre + r;
    let at = field(&prior, &points, &[[far.x, far.y, far.z]]);
    let served = Vector3::new(at[0] as f64, at[1] as f64, at[2] as f64);
    let singular = kelvin(mu, nu, r, total);
    let relative = (served - singular).norm() / singular.norm();
    assert!(
        relative < 0.02,
        "grasp of 6: Kelvinlet {served:?}, Kelvin of the total {singular:?}"
    );
    // Several grasps: one force each.
    let two = Request {
        grasps: vec![
            grasp(m.node_sets["grasp_02"][..6].to_vec(), [0.0, 0.02, 0.0]),
            grasp(m.node_sets["grasp_07"][..6].to_vec(), [0.01, 0.0, -0.01]),
        ],
        ..Request::default()
    };
    let forces = engine.predict(&two).unwrap().grasp_forces.unwrap();
    assert_eq!(forces.len(), 2);
    // Pulling up pulls the first grasper's load up; the second's points the other way in z.
    assert!(forces[0][1] > 0.0 && forces[1][2] < 0.0, "{forces:?}");
}
