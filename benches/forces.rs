//! What grasp forces add to a served request on the embedded phantom, two graspers of 10 nodes
//! (K = 20): the Kelvinlet's point loads from its solved coefficients plus the per-grasp sums, and
//! for green-linear (whose solve yields the point forces anyway) the sums alone; beside them the
//! whole Kelvinlet request through the engine, for scale.

use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use nak::engine::{Engine, Grasp, KelvinletModel, Limits, Request, grasp_totals};
use nak::mesh::{self, MeshSource, TetMesh};
use nak::prior::{InteractionPoints, Kelvinlet, Workspace};

fn two_graspers(mesh: &TetMesh) -> Vec<Grasp> {
    [("grasp_03", [0.01, 0.03, -0.01]), ("grasp_08", [-0.02, 0.02, 0.015])]
        .into_iter()
        .map(|(set, displacement)| Grasp {
            nodes: mesh.node_sets[set].iter().take(10).copied().collect(),
            displacement,
            ..Grasp::default()
        })
        .collect()
}

fn forces(c: &mut Criterion) {
    let mesh = Arc::new(mesh::load(&MeshSource::Embedded).expect("embedded phantom"));
    let grasps = two_graspers(&mesh);
    let mut points = InteractionPoints::default();
    for g in &grasps {
        for &n in &g.nodes {
            points.push(n, mesh.positions[n as usize], g.displacement);
        }
        points.end_grasp();
    }
    let kelvinlet = Kelvinlet::new(mesh.config.prior);
    let model = KelvinletModel::new(&mesh);
    let mut workspace = Workspace::default();
    kelvinlet.solve(&points, &mut workspace).expect("SPD");
    let mut point_forces = Vec::with_capacity(points.len());

    let mut group = c.benchmark_group("forces");
    group.bench_function("kelvinlet K=20", |b| {
        b.iter(|| {
            point_forces.clear();
            model.point_loads(&points, &workspace.coefficients, &mut point_forces);
            grasp_totals(&points, &point_forces).expect("one force per point")
        })
    });
    let solved = point_forces.clone();
    group.bench_function("green-linear K=20", |b| {
        b.iter(|| grasp_totals(&points, &solved).expect("one force per point"))
    });
    let engine = Engine::new(mesh.clone(), Limits::default());
    let request = Request {
        grasps,
        ..Request::default()
    };
    group.bench_function("kelvinlet request K=20", |b| {
        b.iter(|| engine.predict(&request).expect("served"))
    });
    group.finish();
}

criterion_group!(benches, forces);
criterion_main!(benches);
