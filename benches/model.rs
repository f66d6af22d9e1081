//! Per-stage latency of the ONNX test models and the shipped reduced-basis networks (`pod-res*`) on the
//! paper-scale phantom (9,701 nodes), one grasper of ten nodes: the whole prediction in criterion, and
//! the mean prior / network split from the engine's own stage timing; and green-linear at K = 10 and
//! K = 20. Needs ORT_DYLIB_PATH (scripts/onnxruntime-path); green-linear's cache goes to
//! target/green-cache.

use std::path::Path;
use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use nak::engine::{DeformationModel, Engine, Grasp, Limits, Request};
use nak::fem::{GreenFunctions, Stiffness};
use nak::mesh::{self, MeshSource};
use nak::model::GreenModel;

const SHIPPED_REDUCED: [&str; 4] = ["pod-res-fast", "pod-res-lean", "pod-res-big", "pod-res"];
const TEST_MODELS: [&str; 4] = [
    "mlp-residual",
    "mlp-direct-prior",
    "pointnet-residual",
    "pointnet-direct",
];

/// Every model timed: the prior alone, the shipped reduced networks, the test networks.
fn timed_models() -> impl Iterator<Item = &'static str> {
    std::iter::once("kelvinlet").chain(SHIPPED_REDUCED).chain(TEST_MODELS)
}

fn models(c: &mut Criterion) {
    let mesh = Arc::new(mesh::load(&MeshSource::Embedded).expect("embedded phantom"));
    let mut engine = Engine::new(mesh.clone(), Limits::default());
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/models/phantom-liver");
    for model in nak::model::load_all(&dir, &mesh, nak::model::LoadContext::default())
        .expect("test models (is ORT_DYLIB_PATH set?)")
    {
        engine.add_model(Arc::new(model) as Arc<dyn DeformationModel>);
    }
    for name in SHIPPED_REDUCED {
        let shipped = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("models/phantom-liver")
            .join(name);
        let reduced = nak::model::OnnxModel::load(&shipped, &mesh, nak::model::LoadContext::default())
            .expect("the shipped reduced networks");
        engine.add_model(Arc::new(reduced));
    }
    let request = |model: &str| Request {
        model: model.into(),
        grasps: vec![Grasp {
            nodes: mesh.node_sets["grasp_04"].iter().take(10).copied().collect(),
            displacement: [0.0, 0.02, 0.0],
            ..Default::default()
        }],
        ..Default::default()
    };
    let cache = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/green-cache");
    let green =
        GreenFunctions::load_or_compute(&mesh, Stiffness::Linear, &cache, |_, _| {}).expect("Green's functions");
    engine.add_model(Arc::new(GreenModel::new(&mesh, Arc::new(green))));
    let mut group = c.benchmark_group("model");
    // green-linear at the paper's two-grasper size, K = 20.
    let two = Request {
        model: "green-linear".into(),
        grasps: ["grasp_03", "grasp_08"]
            .iter()
            .map(|set| Grasp {
                nodes: mesh.node_sets[*set].iter().take(10).copied().collect(),
                displacement: [0.01, 0.02, 0.0],
                ..Default::default()
            })
            .collect(),
        ..Default::default()
    };
    group.bench_function("green-linear-k20", |b| {
        b.iter(|| engine.predict(&two).expect("prediction"))
    });
    for name in timed_models() {
        let r = request(name);
        group.bench_function(name, |b| b.iter(|| engine.predict(&r).expect("prediction")));
    }
    group.finish();
    // Where the time goes, as the server reports it per request.
    println!("\nmean stage times over 200 requests (µs): model, prior, network, total");
    for name in timed_models() {
        let r = request(name);
        let mut sums = [0.0f64; 3];
        for _ in 0..200 {
            let t = engine.predict(&r).expect("prediction").timing;
            sums[0] += t.prior_us as f64;
            sums[1] += t.network_us as f64;
            sums[2] += t.total_us as f64;
        }
        let [prior, network, total] = sums.map(|s| s / 200.0);
        println!("{name:<18} {prior:>8.0} {network:>8.0} {total:>8.0}");
    }
}

criterion_group!(benches, models);
criterion_main!(benches);
