//! The hyperelastic solver's element loops on the embedded phantom (9,701 nodes, every element):
//! one assembly pass (internal forces and the tangent, what each Newton iteration and predictor
//! costs) and one energy evaluation (what each line-search trial costs), at a smooth deformation
//! of a few percent strain.

use criterion::{Criterion, criterion_group, criterion_main};
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
    group.finish();
}

criterion_group!(benches, fem);
criterion_main!(benches);
