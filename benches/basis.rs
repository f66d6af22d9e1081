//! The reduced basis product Φ g on the embedded phantom liver (9,701 nodes): nak's vectorized,
//! multi-core loop over an f32 and an f16 basis of M = 32 and 64 modes, for every node and for the
//! surface, beside the Kelvinlet prior at K = 20 (what a request pays anyway). The whole residual
//! path of a trained model (encoder in ONNX Runtime + product) is in the `model` bench.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use half::f16;
use nak::mesh::{self, MeshSource, TetMesh};
use nak::model::Basis;
use nak::model::basis::{MESH_HASH_KEY, TENSOR};
use nak::prior::{InteractionPoints, Kelvinlet, NodeCloud, Workspace};
use safetensors::tensor::{Dtype, TensorView};

/// A basis file's bytes: smooth-ish values of millimetre size, [N, 3, M].
fn basis_file(mesh: &TetMesh, modes: usize, dtype: Dtype) -> Vec<u8> {
    let values: Vec<f32> = (0..mesh.node_count() * 3 * modes)
        .map(|i| 1e-3 * ((i as f32) * 0.618).sin())
        .collect();
    let bytes: Vec<u8> = match dtype {
        Dtype::F16 => values.iter().flat_map(|v| f16::from_f32(*v).to_le_bytes()).collect(),
        _ => values.iter().flat_map(|v| v.to_le_bytes()).collect(),
    };
    let view = TensorView::new(dtype, vec![mesh.node_count(), 3, modes], &bytes).expect("tensor");
    let metadata = std::collections::HashMap::from([(MESH_HASH_KEY.to_owned(), mesh.content_hash.clone())]);
    safetensors::serialize([(TENSOR, view)], Some(metadata)).expect("safetensors")
}

fn product(c: &mut Criterion) {
    let mesh = mesh::load(&MeshSource::Embedded).expect("embedded phantom");
    let n = mesh.node_count();
    let mut group = c.benchmark_group("basis");
    group.throughput(Throughput::Elements(n as u64));
    for modes in [32usize, 64] {
        let g: Vec<f32> = (0..modes).map(|m| (m as f32 * 0.37).cos()).collect();
        for (dtype, name) in [(Dtype::F32, "f32"), (Dtype::F16, "f16")] {
            let basis = Basis::parse(&basis_file(&mesh, modes, dtype), &mesh, "bench").expect("basis");
            let mut out = vec![0.0f32; 3 * n];
            group.bench_function(BenchmarkId::new(format!("all-{name}"), modes), |b| {
                b.iter(|| basis.add_product(&g, None, &mut out))
            });
            let surface = &mesh.surface_nodes;
            let mut out = vec![0.0f32; 3 * surface.len()];
            group.bench_function(BenchmarkId::new(format!("surface-{name}"), modes), |b| {
                b.iter(|| basis.add_product(&g, Some(surface), &mut out))
            });
        }
    }
    // The reference a request pays anyway: the prior at K = 20 over every node.
    let kelvinlet = Kelvinlet::new(mesh.config.prior);
    let cloud = NodeCloud::new(mesh.positions.iter().copied());
    let mut points = InteractionPoints::default();
    for (i, &node) in mesh.surface_nodes.iter().step_by(97).take(20).enumerate() {
        points.push(node, mesh.positions[node as usize], [0.01, 0.002 * i as f64, 0.0]);
    }
    let mut workspace = Workspace::default();
    let mut out = vec![0.0f32; 3 * n];
    group.bench_function("prior-k20", |b| {
        b.iter(|| {
            kelvinlet.solve(&points, &mut workspace).expect("SPD");
            kelvinlet.evaluate(&workspace.coefficients, &cloud, &mut out)
        })
    });
    group.finish();
}

criterion_group!(benches, product);
criterion_main!(benches);
