//! The Kelvinlet prior on the embedded phantom liver (~9,700 nodes) for K = 1, 10, 20, 64 interaction
//! points: the coefficient solve, the field evaluation, and both together (what a request pays).
//!
//! Each measurement runs on a thread of rayon's pool, as `nak serve` runs requests: the field then
//! splits its blocks with the pool's other threads from inside, instead of a foreign thread
//! handing the whole field over and waiting for it.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use nak::mesh::{self, MeshSource, TetMesh};
use nak::prior::{InteractionPoints, Kelvinlet, NodeCloud, Workspace};

/// K surface nodes from the grasp regions, in turn, each moved by a different displacement.
fn points(mesh: &TetMesh, k: usize) -> InteractionPoints {
    let regions: Vec<&Vec<u32>> = (1..=10).map(|i| &mesh.node_sets[&format!("grasp_{i:02}")]).collect();
    let mut points = InteractionPoints::default();
    for i in 0..k {
        let node = regions[i % 10][i / 10];
        let t = i as f64;
        points.push(
            node,
            mesh.positions[node as usize],
            [0.01 * t.cos(), 0.02, 0.01 * t.sin()],
        );
    }
    points
}

fn prior(c: &mut Criterion) {
    let mesh = mesh::load(&MeshSource::Embedded).expect("embedded phantom");
    let kelvinlet = Kelvinlet::new(mesh.config.prior);
    let cloud = NodeCloud::new(mesh.positions.iter().copied());
    let mut out = vec![0.0f32; 3 * cloud.len()];
    let mut ws = Workspace::default();
    let mut group = c.benchmark_group("prior");
    group.throughput(Throughput::Elements(cloud.len() as u64));
    for k in [1usize, 10, 20, 64] {
        let p = points(&mesh, k);
        group.bench_with_input(BenchmarkId::new("solve", k), &p, |b, p| {
            rayon::scope(|_| b.iter(|| kelvinlet.solve(p, &mut ws).expect("SPD")))
        });
        kelvinlet.solve(&p, &mut ws).expect("SPD");
        let coefficients = ws.coefficients.clone();
        group.bench_with_input(BenchmarkId::new("field", k), &coefficients, |b, c| {
            rayon::scope(|_| b.iter(|| kelvinlet.evaluate(c, &cloud, &mut out)))
        });
        group.bench_with_input(BenchmarkId::new("solve+field", k), &p, |b, p| {
            rayon::scope(|_| b.iter(|| kelvinlet.solve_and_evaluate(p, &mut ws, &cloud, &mut out).expect("SPD")))
        });
    }
    group.finish();
}

criterion_group!(benches, prior);
criterion_main!(benches);
