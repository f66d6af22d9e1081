//! The hyperelastic solver's parts on the embedded phantom (9,701 nodes, 28,461 unknowns), each what
//! one Newton step pays for: an assembly pass (internal forces and the tangent, each Newton
//! iteration and predictor) and an energy evaluation (each line-search trial), at a smooth
//! deformation of a few percent strain; and the linear algebra of a correction, on the reference
//! tangent (the pattern, ordering and fill of every tangent): a numeric f32 Cholesky
//! factorization, a solve with that factor (the preconditioner, twice a pass over its 44 MB: nak's
//! own sweeps, and faer's supernodal solve they replace) and a product with the f64 tangent (one of
//! each per conjugate-gradient iteration).

use criterion::{Criterion, criterion_group, criterion_main};
use faer::sparse::linalg::matmul::sparse_dense_matmul;
use faer::{Accum, MatMut, MatRef, Par};
use nak::fem::factor::Factor;
use nak::fem::nonlinear::{Hyperelastic, NewtonOptions};
use nak::mesh::{self, MeshSource};

fn fem(c: &mut Criterion) {
    let mesh = mesh::load(&MeshSource::Embedded).expect("embedded phantom");
    let solver = Hyperelastic::new(&mesh, true, NewtonOptions::default()).expect("phantom prepares");
    let u: Vec<[f64; 3]> = mesh
        .positions
        .iter()
        .map(|p| {
            [
                0.05 * p[0] * p[1] / 0.1,
                -0.04 * p[0] * p[0] / 0.1,
                0.03 * p[1] * p[2] / 0.1,
            ]
        })
        .collect();
    let mut group = c.benchmark_group("fem");
    group.sample_size(30);
    group.bench_function("assembly (forces and tangent)", |b| {
        b.iter(|| solver.linearize(&u).expect("no element inverted"))
    });
    group.bench_function("energy", |b| {
        b.iter(|| solver.energy(&u, 1.0).expect("no element inverted"))
    });
    let at_rest = vec![[0.0; 3]; mesh.node_count()];
    let (tangent, _) = solver.linearize(&at_rest).expect("no element inverted");
    let mut factor = solver.tangent_factor::<f32>();
    group.bench_function("factorization (f32)", |b| {
        b.iter(|| {
            factor
                .factorize(tangent.as_ref())
                .expect("the reference tangent is positive definite")
        })
    });
    let n = tangent.nrows();
    let rhs: Vec<f64> = (0..n).map(|i| ((i * 7919) % 1000) as f64 / 1000.0 - 0.5).collect();
    let mut x = rhs.clone();
    group.bench_function("preconditioner solve (f32 factor)", |b| {
        b.iter(|| {
            x.copy_from_slice(&rhs);
            factor.solve_in_place(&mut x);
        })
    });
    group.bench_function("preconditioner solve (f32 factor, faer's own)", |b| {
        b.iter(|| {
            x.copy_from_slice(&rhs);
            factor.solve_with_faer(&mut x);
        })
    });
    let mut product = vec![0.0; n];
    group.bench_function("tangent product (f64)", |b| {
        b.iter(|| {
            sparse_dense_matmul(
                MatMut::from_column_major_slice_mut(&mut product, n, 1),
                Accum::Replace,
                tangent.as_ref(),
                MatRef::from_column_major_slice(&rhs, n, 1),
                1.0,
                Par::Seq,
            )
        })
    });
    group.finish();
}

criterion_group!(benches, fem);
criterion_main!(benches);
