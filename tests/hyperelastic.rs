//! Mooney–Rivlin finite elements against finite differences, the linear solver, an analytic
//! homogeneous stretch and mesh refinement; Newton's energy descent and its handling of inverted
//! elements; corrections from an earlier factor against exact ones, the graspers' neighbourhood
//! eliminated against global Newton alone, and the preconditioner's sweeps against faer's solve.

mod common;

use std::path::Path;

use common::msh_fixture::Fixture;
use faer::Mat;
use nak::fem::factor::Factor;
use nak::fem::hyperelastic::MooneyRivlin;
use nak::fem::nonlinear::{Elimination, Equilibrium, Hyperelastic, Load, NewtonOptions, SolveStats};
use nak::fem::preload::Preloaded;
use nak::fem::{GreenFunctions, LinearSystem, Stiffness, solve_dirichlet};
use nak::mesh::{MeshConfig, TetMesh, VolumetricLaw};
use nak::prior::InteractionPoints;
use nalgebra::Matrix3;

fn mesh(f: &Fixture) -> TetMesh {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/model.toml");
    let config = MeshConfig::parse(&std::fs::read_to_string(path).unwrap(), "model.toml").unwrap();
    TetMesh::from_msh(f.to_msh().as_bytes(), "fixture.msh", config).unwrap()
}

/// Moves `prescribed` nodes from the reference configuration with no body force.
fn solve_without_gravity(m: &TetMesh, prescribed: &[(u32, [f64; 3])]) -> (Hyperelastic, Equilibrium) {
    let solver = Hyperelastic::new(m, false, NewtonOptions::default()).unwrap();
    let start = vec![[0.0; 3]; m.node_count()];
    let result = solver
        .solve(Load {
            start: &start,
            prescribed,
            body_from: 0.0,
            body_to: 0.0,
        })
        .unwrap();
    (solver, result)
}

/// Pulls the `grasp_01` face of `m` by `pull` from the reference configuration while gravity loads.
fn pull_under_gravity(m: &TetMesh, pull: [f64; 3], options: NewtonOptions) -> (Vec<(u32, [f64; 3])>, Equilibrium) {
    let prescribed: Vec<(u32, [f64; 3])> = m.node_sets["grasp_01"].iter().map(|&n| (n, pull)).collect();
    let start = vec![[0.0; 3]; m.node_count()];
    let result = Hyperelastic::new(m, true, options)
        .unwrap()
        .solve(Load {
            start: &start,
            prescribed: &prescribed,
            body_from: 0.0,
            body_to: 1.0,
        })
        .unwrap();
    (prescribed, result)
}

const LAWS: [VolumetricLaw; 2] = [VolumetricLaw::LnJSquared, VolumetricLaw::JMinusOneSquared];

fn liver(volumetric: VolumetricLaw) -> MooneyRivlin {
    MooneyRivlin::new(1620.0, 1970.0, 0.45, volumetric)
}

/// A generic deformation gradient with J ≈ 1.1, sheared and rotated.
fn deformation() -> Matrix3<f64> {
    Matrix3::new(1.10, 0.15, -0.05, -0.08, 0.95, 0.12, 0.04, -0.10, 1.06)
}

fn largest(values: impl IntoIterator<Item = f64>) -> f64 {
    values.into_iter().fold(0.0, |m, v| m.max(v.abs()))
}

/// Central differences with h = 1e-6 leave O(h²) ≈ 1e-12 truncation and ~1e-10 round-off relative
/// to these stresses (kPa): 1e-6 relative separates a correct derivative from a wrong one by orders.
const DIFFERENCE_TOLERANCE: f64 = 1e-6;

/// A compressed one, J ≈ 0.3, where the two volumetric laws differ most.
fn compression() -> Matrix3<f64> {
    Matrix3::new(0.62, 0.10, -0.04, -0.06, 0.70, 0.08, 0.03, -0.05, 0.72)
}

#[test]
fn stress_and_tangent_are_the_derivatives_of_the_energy() {
    for (law, f) in LAWS
        .iter()
        .flat_map(|&v| [(liver(v), deformation()), (liver(v), compression())])
    {
        let (p, a) = law.stress_and_tangent(&f).unwrap();
        let h = 1e-6;
        for k in 0..3 {
            for l in 0..3 {
                let mut plus = f;
                plus[(k, l)] += h;
                let mut minus = f;
                minus[(k, l)] -= h;
                let dw = (law.energy(&plus).unwrap() - law.energy(&minus).unwrap()) / (2.0 * h);
                assert!(
                    (dw - p[(k, l)]).abs() <= DIFFERENCE_TOLERANCE * largest(p.iter().copied()),
                    "{:?}: P[{k}{l}] = {} vs dW/dF = {dw}",
                    law.volumetric,
                    p[(k, l)]
                );
                let dp = (law.stress(&plus).unwrap() - law.stress(&minus).unwrap()) / (2.0 * h);
                let scale = largest(a.iter().flatten().copied());
                for i in 0..3 {
                    for j in 0..3 {
                        let exact = a[3 * i + j][3 * k + l];
                        assert!(
                            (dp[(i, j)] - exact).abs() <= DIFFERENCE_TOLERANCE * scale,
                            "{:?}: A[{i}{j}][{k}{l}] = {exact} vs {}",
                            law.volumetric,
                            dp[(i, j)]
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn the_log_law_is_a_barrier_and_agrees_with_the_quadratic_one_near_the_reference() {
    // Uniform compression to volume ratio J: the isochoric terms vanish, U(J) is all that is left.
    let squeeze = |j: f64| Matrix3::from_diagonal_element(j.cbrt());
    let [log, quadratic] = LAWS.map(liver);
    // To second order at J = 1 the laws are one: ln J = (J − 1) − (J − 1)²/2 + …, so their
    // energies differ by O((J − 1)³) ...
    for x in [1e-2f64, 1e-3] {
        let (a, b) = (
            log.energy(&squeeze(1.0 - x)).unwrap(),
            quadratic.energy(&squeeze(1.0 - x)).unwrap(),
        );
        assert!(
            (a - b).abs() <= 0.6 * log.kappa * x.powi(3),
            "J = {}: {a} vs {b}",
            1.0 - x
        );
    }
    // ... while towards J = 0 only the log law's energy grows without bound.
    let (a, b) = (
        log.energy(&squeeze(1e-6)).unwrap(),
        quadratic.energy(&squeeze(1e-6)).unwrap(),
    );
    assert!(a > 50.0 * b, "{a} vs {b}");
}

#[test]
fn the_reference_state_is_stress_free_and_inverted_states_are_refused() {
    let law = liver(VolumetricLaw::LnJSquared);
    assert!(largest(law.stress(&Matrix3::identity()).unwrap().iter().copied()) < 1e-9);
    assert_eq!(law.energy(&Matrix3::identity()), Some(0.0));
    let mirrored = Matrix3::from_diagonal(&nalgebra::Vector3::new(-1.0, 1.0, 1.0));
    assert!(law.energy(&mirrored).is_none());
    assert!(law.stress_and_tangent(&mirrored).is_none());
}

#[test]
fn assembled_tangent_matches_differences_of_the_internal_force() {
    let m = mesh(&Fixture::bar([3, 2, 2], [0.01; 3]));
    let solver = Hyperelastic::new(&m, true, NewtonOptions::default()).unwrap();
    // A smooth, finite deformation: bending plus twist, well away from inversion.
    let u: Vec<[f64; 3]> = m
        .positions
        .iter()
        .map(|p| {
            [
                0.1 * p[0] * p[1] / 0.02,
                -0.2 * p[0] * p[0] / 0.03,
                0.15 * p[0] * p[2] / 0.02,
            ]
        })
        .collect();
    let (tangent, _) = solver.linearize(&u).unwrap();
    let dense = tangent.to_dense();
    let dofs = solver.dofs();
    let h = 1e-7;
    let scale = largest(dense.col_iter().flat_map(|c| c.iter().copied().collect::<Vec<_>>()));
    for node in [5u32, 17, 22, 35] {
        for c in 0..3 {
            let Some(col) = dofs.get(node, c) else { continue };
            let shifted = |sign: f64| {
                let mut v = u.clone();
                v[node as usize][c] += sign * h;
                solver.linearize(&v).unwrap().1
            };
            let (plus, minus) = (shifted(1.0), shifted(-1.0));
            for n in 0..m.node_count() as u32 {
                for k in 0..3 {
                    let Some(row) = dofs.get(n, k) else { continue };
                    let difference = (plus[n as usize][k] - minus[n as usize][k]) / (2.0 * h);
                    assert!(
                        (difference - dense[(row, col)]).abs() <= DIFFERENCE_TOLERANCE * scale,
                        "K[{row}][{col}] = {} vs {difference}",
                        dense[(row, col)]
                    );
                }
            }
        }
    }
}

#[test]
fn small_displacements_match_the_linear_solver() {
    let mut m = mesh(&Fixture::bar([4, 2, 2], [0.01; 3]));
    // The linear material the Mooney–Rivlin law linearizes to.
    for material in m.config.materials.values_mut() {
        material.shear_modulus = 2.0 * (material.c10 + material.c01);
    }
    let tip = [2e-7, -3e-7, 1e-7];
    let prescribed: Vec<(u32, [f64; 3])> = m.node_sets["grasp_01"].iter().map(|&n| (n, tip)).collect();
    let linear = solve_dirichlet(&m, &prescribed).unwrap();
    let (_, nonlinear) = solve_without_gravity(&m, &prescribed);
    let scale = largest(linear.iter().flatten().copied());
    let difference = largest(
        linear
            .iter()
            .zip(&nonlinear.displacement)
            .flat_map(|(a, b)| (0..3).map(move |k| a[k] - b[k])),
    );
    // Strains are ~1e-5, so the geometric and material nonlinearity is ~1e-5 relative.
    assert!(
        difference <= 1e-3 * scale,
        "difference {difference:e} vs field {scale:e}"
    );
}

/// ∂W/∂λ_i for principal stretches, from the energy written in stretches (independent of the tensor
/// code): the first Piola–Kirchhoff stress of a diagonal deformation.
fn principal_stress(law: &MooneyRivlin, s: [f64; 3]) -> [f64; 3] {
    let j = s[0] * s[1] * s[2];
    let i1 = s.iter().map(|x| x * x).sum::<f64>();
    let i2 = s[0].powi(2) * s[1].powi(2) + s[1].powi(2) * s[2].powi(2) + s[0].powi(2) * s[2].powi(2);
    std::array::from_fn(|k| {
        let others = i1 - s[k] * s[k];
        // J U′(J): ∂U/∂λ_k = U′(J) J / λ_k.
        let volumetric = match law.volumetric {
            VolumetricLaw::LnJSquared => law.kappa * j.ln(),
            VolumetricLaw::JMinusOneSquared => law.kappa * (j - 1.0) * j,
        };
        law.c10 * j.powf(-2.0 / 3.0) * (2.0 * s[k] - 2.0 / 3.0 * i1 / s[k])
            + law.c01 * j.powf(-4.0 / 3.0) * (2.0 * s[k] * others - 4.0 / 3.0 * i2 / s[k])
            + volumetric / s[k]
    })
}

#[test]
fn a_cube_in_uniaxial_stretch_carries_the_analytic_mooney_rivlin_stress() {
    let mut fixture = Fixture::grid(2);
    // Hold only the corner at the origin (it does not move under F); prescribe the rest of the surface.
    fixture.sets[0].1 = vec![0];
    let m = mesh(&fixture);
    let law = MooneyRivlin::from_material(&m.config.materials["liver"], m.config.volumetric_law);
    let stretch = 1.3;
    // Lateral stretch with zero lateral stress, by bisection on the analytic stress.
    let (mut low, mut high) = (0.5, 1.0);
    for _ in 0..200 {
        let mid = 0.5 * (low + high);
        if principal_stress(&law, [stretch, mid, mid])[1] > 0.0 {
            high = mid;
        } else {
            low = mid;
        }
    }
    let lateral = 0.5 * (low + high);
    let s = [stretch, lateral, lateral];
    let exact = |p: [f64; 3]| std::array::from_fn::<f64, 3, _>(|k| (s[k] - 1.0) * p[k]);
    let prescribed: Vec<(u32, [f64; 3])> = m
        .surface_nodes
        .iter()
        .filter(|&&n| n != 0)
        .map(|&n| (n, exact(m.positions[n as usize])))
        .collect();
    let (_, result) = solve_without_gravity(&m, &prescribed);
    // P1 elements represent the homogeneous field exactly: the interior node sits where F puts it.
    let centre = (0..m.node_count()).find(|&n| !m.is_surface[n]).unwrap();
    let want = exact(m.positions[centre]);
    for (got, want) in result.displacement[centre].iter().zip(want) {
        assert!((got - want).abs() < 1e-10);
    }
    // The reactions on the face x = 0.02 m add up to P11 times its reference area.
    let face_force: f64 = prescribed
        .iter()
        .zip(&result.reactions)
        .filter(|((n, _), _)| (m.positions[*n as usize][0] - 0.02).abs() < 1e-12)
        .map(|(_, r)| r[0])
        .sum();
    let p11 = principal_stress(&law, s)[0];
    let area = 0.02 * 0.02;
    assert!(
        (face_force - p11 * area).abs() <= 1e-8 * (p11 * area).abs(),
        "face force {face_force} N vs P11·A = {} N",
        p11 * area
    );
    // And the stress itself, from the tensor code, is uniaxial.
    let f = Matrix3::from_diagonal(&nalgebra::Vector3::from(s));
    let p = law.stress(&f).unwrap();
    assert!((p[(0, 0)] - p11).abs() < 1e-9 * p11.abs());
    assert!(p[(1, 1)].abs() < 1e-6 * p11.abs() && p[(2, 2)].abs() < 1e-6 * p11.abs());
}

#[test]
fn newton_decreases_the_energy_and_converges_under_gravity_and_a_large_grasp() {
    let m = mesh(&Fixture::bar([6, 2, 2], [0.01; 3]));
    let (prescribed, result) = pull_under_gravity(&m, [0.02, 0.03, -0.015], NewtonOptions::default());
    assert!(result.stats.newton_iterations >= 2);
    let mut checked = 0;
    for step in 0..result.stats.load_steps + result.stats.step_cuts {
        // The first record of a step is its predictor, taken at the previous step's constraints.
        let energies: Vec<f64> = result
            .iterations
            .iter()
            .filter(|i| i.load_step == step)
            .skip(1)
            .map(|i| i.energy)
            .collect();
        for pair in energies.windows(2) {
            assert!(pair[1] <= pair[0] + 1e-12 * pair[0].abs(), "energy rose: {pair:?}");
            checked += 1;
        }
    }
    assert!(checked >= 1);
    for (n, target) in &prescribed {
        assert_eq!(&result.displacement[*n as usize], target);
    }
}

/// The grasp face's centre node of the 30 mm cube.
fn poked_node(m: &TetMesh) -> u32 {
    m.node_sets["grasp_01"]
        .iter()
        .copied()
        .find(|&n| {
            let p = m.positions[n as usize];
            (p[1] - 0.01).abs() < 1e-9 && (p[2] - 0.01).abs() < 1e-9
        })
        .unwrap()
}

/// Pushes the grasp face's centre node of a 30 mm cube (cells of 10 mm) 25 mm in, without gravity.
fn deep_poke(elimination: Option<Elimination>) -> (Hyperelastic, Equilibrium) {
    let m = mesh(&Fixture::grid(3));
    let centre = poked_node(&m);
    let options = NewtonOptions {
        elimination,
        ..NewtonOptions::default()
    };
    let solver = Hyperelastic::new(&m, false, options).unwrap();
    let start = vec![[0.0; 3]; m.node_count()];
    let result = solver
        .solve(Load {
            start: &start,
            prescribed: &[(centre, [-0.025, 0.0, 0.0])],
            body_from: 0.0,
            body_to: 0.0,
        })
        .unwrap();
    (solver, result)
}

#[test]
fn a_deep_poke_is_solved_with_feasible_steps_only() {
    // The linear predictor over the whole load would fold the elements around the node: solved
    // globally, it is shortened to stop short of the first collapse; with the node's neighbourhood
    // eliminated, that neighbourhood follows by local steps. Either way no trial state inverts.
    for elimination in [None, Some(Elimination::default())] {
        let (solver, result) = deep_poke(elimination);
        if elimination.is_none() {
            assert!(result.stats.shortened_predictors > 0, "{:?}", result.stats);
        }
        assert_eq!(result.stats.inverted_trials, 0, "{:?}", result.stats);
        assert!(solver.energy(&result.displacement, 0.0).is_some());
    }
}

#[test]
fn every_state_on_the_load_path_is_the_equilibrium_of_its_share_of_the_load() {
    // `nak datagen` keeps the load steps' converged states as samples of their own loads: each must
    // be what a solve of that load alone reaches. They end at the intermediate tolerance (a residual
    // of 1e-3 of the load's scale), a whole solve tighter; measured here 1e-7 to 2.2e-5 (relative L2).
    let (solver, result) = deep_poke(Some(Elimination::default()));
    assert!(result.path.len() >= 2, "{} states", result.path.len());
    let loads: Vec<f64> = result.path.iter().map(|s| s.load).collect();
    assert!(
        loads.windows(2).all(|w| w[0] < w[1]) && loads[0] > 0.0 && loads[loads.len() - 1] < 1.0,
        "{loads:?}"
    );
    let (centre, start) = (
        poked_node(&mesh(&Fixture::grid(3))),
        vec![[0.0; 3]; solver.node_count()],
    );
    for state in &result.path {
        let direct = solver
            .solve(Load {
                start: &start,
                prescribed: &[(centre, [-0.025 * state.load, 0.0, 0.0])],
                body_from: 0.0,
                body_to: 0.0,
            })
            .unwrap();
        let difference = relative_difference(&state.displacement, &direct.displacement);
        assert!(
            difference < 1e-4,
            "load {}: {difference:.2e} from its own solve",
            state.load
        );
    }
}

#[test]
fn newton_restarted_from_a_converged_state_stays_there() {
    let m = mesh(&Fixture::bar([6, 2, 2], [0.01; 3]));
    let (prescribed, first) = pull_under_gravity(&m, [0.03, 0.04, -0.02], NewtonOptions::default());
    let again = Hyperelastic::new(&m, true, NewtonOptions::default())
        .unwrap()
        .solve(Load {
            start: &first.displacement,
            prescribed: &prescribed,
            body_from: 1.0,
            body_to: 1.0,
        })
        .unwrap();
    // The field is where the path ends, not how it got there: a second solve from it moves nothing
    // beyond the convergence tolerance's share of the field.
    let scale = largest(first.displacement.iter().flatten().copied());
    let moved = first
        .displacement
        .iter()
        .zip(&again.displacement)
        .flat_map(|(a, b)| (0..3).map(move |k| (a[k] - b[k]).abs()))
        .fold(0.0, f64::max);
    assert!(moved <= 1e-9 * scale, "moved {moved:e} m; {:?}", again.stats);
}

#[test]
fn corrections_from_an_earlier_factor_reach_the_same_equilibrium_with_fewer_factorizations() {
    let m = mesh(&Fixture::bar([8, 3, 3], [0.01; 3]));
    let solve = |reuse_factorization| {
        let options = NewtonOptions {
            reuse_factorization,
            ..NewtonOptions::default()
        };
        pull_under_gravity(&m, [0.03, 0.04, -0.02], options).1
    };
    let (reused, exact) = (solve(true), solve(false));
    assert!(reused.stats.krylov_iterations > 0, "{:?}", reused.stats);
    assert_eq!(exact.stats.krylov_iterations, 0);
    same_equilibrium_for_less(&reused, &exact, |s| s.factorizations);
}

/// `cheaper` reaches `reference`'s equilibrium with less of what `cost` counts. Both stop at
/// ‖r‖ ≤ 1e-6 of the load; the displacement each leaves undone is about that fraction of the field,
/// so two answers agree to a few 1e-6 of it.
fn same_equilibrium_for_less(cheaper: &Equilibrium, reference: &Equilibrium, cost: fn(&SolveStats) -> usize) {
    assert!(
        cost(&cheaper.stats) < cost(&reference.stats),
        "{:?} against {:?}",
        cheaper.stats,
        reference.stats
    );
    let relative = relative_difference(&cheaper.displacement, &reference.displacement);
    assert!(relative < 1e-5, "relative difference {relative:.2e}");
}

#[test]
fn eliminating_the_grasps_neighbourhood_reaches_the_same_equilibrium_in_fewer_global_iterations() {
    let (_, eliminated) = deep_poke(Some(Elimination::default()));
    let (_, global) = deep_poke(None);
    assert!(eliminated.stats.local_iterations > 0, "{:?}", eliminated.stats);
    assert_eq!(global.stats.local_iterations, 0);
    same_equilibrium_for_less(&eliminated, &global, |s| s.newton_iterations);
}

#[test]
fn the_preconditioners_own_sweeps_solve_as_faer_does() {
    // The phantom's tangent at rest in f32 (4,047 supernodes, most one node wide): its sweeps and
    // faer's supernodal solve agree to the f32 round-off of the factor.
    let m = nak::mesh::load(&nak::mesh::MeshSource::Embedded).unwrap();
    let solver = Hyperelastic::new(&m, true, NewtonOptions::default()).unwrap();
    let (tangent, _) = solver.linearize(&vec![[0.0; 3]; m.node_count()]).unwrap();
    let mut factor = solver.tangent_factor::<f32>();
    factor.factorize(tangent.as_ref()).unwrap();
    let rhs: Vec<f64> = (0..tangent.nrows())
        .map(|i| ((i * 7919) % 1000) as f64 / 1000.0 - 0.5)
        .collect();
    let (mut swept, mut reference) = (rhs.clone(), rhs);
    factor.solve_in_place(&mut swept);
    factor.solve_with_faer(&mut reference);
    let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
    let difference: Vec<f64> = swept.iter().zip(&reference).map(|(a, b)| a - b).collect();
    let relative = norm(&difference) / norm(&reference);
    assert!(relative < 1e-5, "relative difference {relative:.2e}");
}

/// The bar solved with gravity and its free face pulled, on cells of `h`: the displacement of the
/// node at (4 cm, 0, 0), present at every level, and the grasp face's total reaction.
fn bar_under_gravity_and_pull(h: f64) -> ([f64; 3], [f64; 3]) {
    let cells = |length: f64| (length / h).round() as usize;
    let m = mesh(&Fixture::bar([cells(0.06), cells(0.02), cells(0.02)], [h; 3]));
    let (_, result) = pull_under_gravity(&m, [0.010, 0.015, -0.005], NewtonOptions::default());
    let probe = (0..m.node_count())
        .find(|&n| {
            let p = m.positions[n];
            (p[0] - 0.04).abs() < 1e-9 && p[1].abs() < 1e-9 && p[2].abs() < 1e-9
        })
        .unwrap();
    let reaction = result
        .reactions
        .iter()
        .fold([0.0; 3], |sum, r| std::array::from_fn(|k| sum[k] + r[k]));
    (result.displacement[probe], reaction)
}

#[test]
fn the_answer_converges_as_the_mesh_refines() {
    // An independent check of the discretization: halving the cells four times, the answer must
    // settle. Observed (release build): the probe moves 0.78, 0.39, 0.12 mm between levels (ratios
    // 2.0 and 3.3, towards P1's h² at nodes) and the reaction changes 0.131, 0.077, 0.038 N (ratios
    // 1.7 and 2.1: first order, as the traction concentrates at the grasp face's edges). Each change
    // at least 1.5 times smaller than the one before, and the last below 2 % of the displacement,
    // holds with margin for a converging solver and fails for one whose answer does not settle.
    let distance = |a: [f64; 3], b: [f64; 3]| (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt();
    let levels = [0.02, 0.01, 0.005, 0.0025].map(bar_under_gravity_and_pull);
    let changes: Vec<(f64, f64)> = levels
        .windows(2)
        .map(|pair| (distance(pair[0].0, pair[1].0), distance(pair[0].1, pair[1].1)))
        .collect();
    for pair in changes.windows(2) {
        let (before, after) = (pair[0], pair[1]);
        assert!(after.0 * 1.5 < before.0, "displacement changes {changes:?}");
        assert!(after.1 * 1.5 < before.1, "reaction changes {changes:?}");
    }
    let finest = levels[3].0;
    let size = distance(finest, [0.0; 3]);
    assert!(
        changes[2].0 < 0.02 * size,
        "last change {:.2e} m of {size:.2e} m",
        changes[2].0
    );
}

/// Relative L2 difference of two nodal fields.
fn relative_difference(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
    let norm = |u: &mut dyn Iterator<Item = f64>| u.map(|v| v * v).sum::<f64>().sqrt();
    norm(&mut a.iter().zip(b).flat_map(|(x, y)| (0..3).map(move |k| x[k] - y[k])))
        / norm(&mut b.iter().flatten().copied())
}

#[test]
fn green_tangent_is_the_nonlinear_answer_to_first_order() {
    // On the coarse phantom under gravity: grasps of 2 and 1 mm solved by Newton from the preloaded
    // state, against green-tangent (the tangent there, inverted through Green's functions) and
    // green-linear (the reference configuration's linear elasticity).
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver/liver-coarse.msh");
    let m = nak::mesh::load(&nak::mesh::MeshSource::File(path)).unwrap();
    let cache = tempfile::tempdir().unwrap();
    let tangent = GreenFunctions::load_or_compute(&m, Stiffness::PreloadTangent, cache.path(), |_, _| {}).unwrap();
    let linear = GreenFunctions::load_or_compute(&m, Stiffness::Linear, cache.path(), |_, _| {}).unwrap();
    let preloaded = Preloaded::load_or_compute(&m, cache.path(), NewtonOptions::default()).unwrap();
    assert!(
        preloaded.solved.is_none(),
        "green-tangent left the preloaded state in the cache"
    );
    let nodes: Vec<u32> = m.node_sets["grasp_03"].iter().take(6).copied().collect();
    let served = |green: &GreenFunctions, u: [f64; 3]| {
        let mut points = InteractionPoints::default();
        for &n in &nodes {
            points.push(n, m.positions[n as usize], u);
        }
        let mut out = vec![0.0f32; 3 * m.node_count()];
        green
            .solve(&points.nodes, &points.displacements, None, &mut out, &mut Vec::new())
            .unwrap();
        out.chunks(3)
            .map(|c| [c[0], c[1], c[2]].map(f64::from))
            .collect::<Vec<_>>()
    };
    let errors: Vec<(f64, f64)> = [2e-3, 1e-3]
        .into_iter()
        .map(|amplitude| {
            let u = [0.6, 0.64, -0.48].map(|d| d * amplitude);
            let grasped: Vec<(u32, [f64; 3])> = nodes.iter().map(|&n| (n, u)).collect();
            let truth = preloaded.grasp(&grasped).unwrap().displacement;
            (
                relative_difference(&served(&tangent, u), &truth),
                relative_difference(&served(&linear, u), &truth),
            )
        })
        .collect();
    // The tangent's error is the nonlinear remainder, O(amplitude): halving the grasp halves it
    // (observed 2.4e-2 and 1.2e-2; a tangent missing a term would leave an error that does not
    // shrink). green-linear misses the sagged geometry and the weight's initial stress, an error
    // that does not shrink with the grasp either (observed 0.16 at both).
    let (tangent_error, linear_error) = errors[1];
    assert!(tangent_error < 0.03, "{errors:?}");
    let ratio = errors[1].0 / errors[0].0;
    assert!((0.4..0.6).contains(&ratio), "not first order: {errors:?}");
    assert!(linear_error > 5.0 * tangent_error, "{errors:?}");
}

#[test]
fn green_tangents_forces_are_the_tangent_stiffness_times_its_field() {
    // green-tangent serves f = (G[S,S])⁻¹ u_S at the held nodes S. Against it: the same capacitance
    // solve in f64 on a fresh factorization of the preload tangent, and K_t u of that f64 field taken
    // element by element, as the central difference of the elements' internal forces about the
    // preloaded state (no assembled matrix involved).
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver/liver-coarse.msh");
    let m = nak::mesh::load(&nak::mesh::MeshSource::File(path)).unwrap();
    let cache = tempfile::tempdir().unwrap();
    let green = GreenFunctions::load_or_compute(&m, Stiffness::PreloadTangent, cache.path(), |_, _| {}).unwrap();
    let preloaded = Preloaded::load_or_compute(&m, cache.path(), NewtonOptions::default()).unwrap();
    let held: Vec<u32> = m.node_sets["grasp_03"].iter().take(6).copied().collect();
    let moved = [[0.6e-3, 0.64e-3, -0.48e-3]; 6];
    let mut served = Vec::new();
    let mut unused = vec![0.0f32; 3];
    green
        .solve(&held, &moved, Some(&held[..1]), &mut unused, &mut served)
        .unwrap();

    let (tangent, _) = preloaded.solver.linearize(&preloaded.rest).unwrap();
    let system = LinearSystem::from_stiffness(preloaded.solver.dofs().clone(), &tangent).unwrap();
    let dofs = &system.dofs;
    let k = 3 * held.len();
    let mut columns = Mat::<f64>::zeros(dofs.len(), k);
    for (j, &n) in held.iter().enumerate() {
        for c in 0..3 {
            columns[(dofs.get(n, c).unwrap(), 3 * j + c)] = 1.0;
        }
    }
    system.solve_in_place(&mut columns);
    let gss = nalgebra::DMatrix::from_fn(k, k, |r, c| columns[(dofs.get(held[r / 3], r % 3).unwrap(), c)]);
    let u_s = nalgebra::DVector::from_iterator(k, moved.iter().flatten().copied());
    let forces = gss.cholesky().unwrap().solve(&u_s);
    let field: Vec<[f64; 3]> = (0..m.node_count() as u32)
        .map(|n| {
            std::array::from_fn(|c| {
                dofs.get(n, c)
                    .map_or(0.0, |d| (0..k).map(|j| columns[(d, j)] * forces[j]).sum())
            })
        })
        .collect();

    let step = 1e-2;
    let shifted = |sign: f64| -> Vec<[f64; 3]> {
        let state: Vec<[f64; 3]> = preloaded
            .rest
            .iter()
            .zip(&field)
            .map(|(r, u)| std::array::from_fn(|c| r[c] + sign * step * u[c]))
            .collect();
        preloaded.solver.linearize(&state).unwrap().1
    };
    let (plus, minus) = (shifted(1.0), shifted(-1.0));
    let stiffness_times_field =
        |n: u32| -> [f64; 3] { std::array::from_fn(|c| (plus[n as usize][c] - minus[n as usize][c]) / (2.0 * step)) };
    let size = forces.norm();
    for (j, &n) in held.iter().enumerate() {
        let exact = [forces[3 * j], forces[3 * j + 1], forces[3 * j + 2]];
        let element_wise = stiffness_times_field(n);
        for c in 0..3 {
            // f64 capacitance solve against the elements' K_t u: difference and solver error only.
            assert!(
                (element_wise[c] - exact[c]).abs() < 1e-6 * size,
                "node {n}: {element_wise:?} against {exact:?}"
            );
            // Served: Green's functions stored in f32, so G[S,S] carries f32 rounding into the solve.
            assert!(
                (served[j][c] - exact[c]).abs() < 1e-3 * size,
                "node {n}: served {:?} against {exact:?}",
                served[j]
            );
        }
    }
    // Elsewhere the field is in equilibrium: K_t u vanishes at the free nodes.
    let largest_free = (0..m.node_count() as u32)
        .filter(|n| !held.contains(n) && dofs.get(*n, 0).is_some())
        .map(|n| stiffness_times_field(n).iter().map(|v| v * v).sum::<f64>().sqrt())
        .fold(0.0, f64::max);
    assert!(
        largest_free < 1e-6 * size,
        "{largest_free} N at a free node, against {size} N held"
    );
}
