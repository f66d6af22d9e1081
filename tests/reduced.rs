//! Models of the `interaction` form (docs/design.md §7): the graph reads only the K interaction points and
//! gives the field, or coefficients of a basis beside it that nak multiplies. The three coarse test
//! models share one encoder and one basis: nak's product (f32 and f16 storage) is checked against ONNX
//! Runtime's own MatMul over the same basis folded into the graph.
//!
//! Needs ONNX Runtime: ORT_DYLIB_PATH must name libonnxruntime.so.1.31.1 (scripts/test sets it).

mod common;

use common::models::{coarse, copy_model, engine_with_models, load_error, predict, test_models, two_graspers};
use common::server::TestServer;
use std::sync::Arc;

use nak::engine::{Grasp, Request, Selection};
use nak::model::OnnxModel;
use nak::proto::v1 as pb;

fn largest(field: &[f32]) -> f32 {
    field.iter().fold(0.0f32, |m, v| m.max(v.abs()))
}

fn max_difference(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

/// nak's product over the f32 basis equals ONNX Runtime's MatMul over the same basis in the graph, to
/// f32 rounding of a 12-term sum (1e-5 of the field); f16 storage rounds each basis value to 2⁻¹¹
/// relative, so the field moves by at most ~1e-3 of its size.
#[test]
fn the_basis_product_equals_onnx_runtimes_matmul_over_the_folded_basis() {
    let engine = engine_with_models(coarse());
    let prior = predict(&engine, "kelvinlet", Selection::All);
    let folded = predict(&engine, "reduced-folded", Selection::All);
    let product = predict(&engine, "reduced-residual", Selection::All);
    let half = predict(&engine, "reduced-residual-f16", Selection::All);
    let scale = largest(&folded);
    let residual: Vec<f32> = folded.iter().zip(&prior).map(|(a, b)| a - b).collect();
    assert!(
        largest(&residual) > 1e-3,
        "the network adds nothing: {}",
        largest(&residual)
    );
    let d = max_difference(&product, &folded);
    assert!(d <= 1e-5 * scale, "f32 basis vs folded graph: {d} of {scale}");
    let d = max_difference(&half, &folded);
    assert!(
        d <= 1e-3 * largest(&residual) && d > 0.0,
        "f16 basis vs folded graph: {d}"
    );
}

#[test]
fn selections_are_rows_of_the_full_field() {
    let engine = engine_with_models(coarse());
    let mesh = engine.mesh().clone();
    for model in ["reduced-residual", "reduced-residual-f16", "reduced-folded"] {
        let full = predict(&engine, model, Selection::All);
        let nodes = vec![3u32, 2000, 17, 3];
        let surface = predict(&engine, model, Selection::Surface);
        let listed = predict(&engine, model, Selection::List(nodes.clone()));
        let rows = mesh.surface_nodes.iter().zip(surface.chunks_exact(3));
        for (&n, row) in nodes.iter().zip(listed.chunks_exact(3)).chain(rows) {
            let expected = &full[3 * n as usize..3 * n as usize + 3];
            assert!(
                max_difference(row, expected) <= 1e-6,
                "{model} node {n}: {row:?} vs {expected:?}"
            );
        }
    }
}

/// K is dynamic: one point and the server's limit both run, and the field changes with K.
#[test]
fn any_number_of_points_up_to_the_limit_runs_and_more_are_refused() {
    let engine = engine_with_models(coarse());
    let mesh = engine.mesh().clone();
    let limit = engine.limits().max_interaction_points;
    let request = |k: usize| Request {
        model: "reduced-residual".into(),
        grasps: vec![Grasp {
            nodes: mesh
                .surface_nodes
                .iter()
                .copied()
                .filter(|&n| !mesh.is_fixed(n))
                .take(k)
                .collect(),
            displacement: [0.0, 0.01, 0.0],
            ..Default::default()
        }],
        ..Default::default()
    };
    let one = engine.predict(&request(1)).unwrap();
    let many = engine.predict(&request(limit)).unwrap();
    assert_eq!((one.interaction_points, many.interaction_points), (1, limit));
    assert!(max_difference(&one.displacements, &many.displacements) > 1e-4);
    let err = engine.predict(&request(limit + 1)).unwrap_err().to_string();
    assert!(err.contains(&limit.to_string()), "{err}");
}

#[test]
fn refuses_a_wrong_interaction_input_or_basis() {
    let faulty = test_models().join("faulty");
    let err = load_error(&faulty.join("interaction-wrong-width/interaction-wrong-width"));
    assert!(
        err.contains("\"interaction\" has 5 values a point")
            && err.contains("6 (position, displacement), 10 (then normal, nodal volume) or 11"),
        "{err}"
    );
    // A symbolic width would leave nak to guess which of the three the graph reads.
    let err = load_error(&faulty.join("interaction-symbolic-width/interaction-symbolic-width"));
    assert!(
        err.contains("\"interaction\" has a symbolic number of values a point") && err.contains("or 11"),
        "{err}"
    );
    let err = load_error(&faulty.join("basis-wrong-size/basis-wrong-size"));
    let n = coarse().node_count();
    assert!(
        err.contains("basis.safetensors") && err.contains(&format!("[{}, 3, 12]", n - 1)),
        "{err}"
    );
    let err = load_error(&faulty.join("basis-other-mesh/basis-other-mesh"));
    assert!(err.contains("basis.safetensors: made for mesh"), "{err}");
    let err = load_error(&faulty.join("basis-modes-mismatch/basis-modes-mismatch"));
    assert!(err.contains("has 8 modes; the graph gives 12 coefficients"), "{err}");

    let (_root, dir) = copy_model("reduced-residual");
    std::fs::remove_file(dir.join("basis.safetensors")).unwrap();
    let err = load_error(&dir);
    assert!(err.contains("basis.safetensors: missing"), "{err}");

    let (_root, dir) = copy_model("reduced-residual");
    let bytes = std::fs::read(dir.join("basis.safetensors")).unwrap();
    std::fs::write(dir.join("basis.safetensors"), &bytes[..bytes.len() / 2]).unwrap();
    let err = load_error(&dir);
    assert!(err.contains("basis.safetensors: not a safetensors file"), "{err}");

    // A basis beside a graph that gives the field itself: ambiguous, refused.
    let (_root, dir) = copy_model("reduced-folded");
    std::fs::write(dir.join("basis.safetensors"), bytes).unwrap();
    let err = load_error(&dir);
    assert!(
        err.contains("a basis beside a graph whose output is \"displacement\""),
        "{err}"
    );

    // The manifest must say which input the graph reads.
    let (_root, dir) = copy_model("reduced-residual");
    let manifest = std::fs::read_to_string(dir.join("manifest.toml")).unwrap();
    let features = manifest.replace(r#"["interaction"]"#, r#"["position", "displacement", "active"]"#);
    std::fs::write(dir.join("manifest.toml"), features).unwrap();
    let err = load_error(&dir);
    assert!(
        err.contains("does not match the graph, whose input is \"interaction\""),
        "{err}"
    );
}

#[tokio::test]
async fn served_over_grpc_with_the_basis_listed() {
    let server = TestServer::with_engine(engine_with_models(coarse()), 1 << 20).await;
    let mut client = server.client().await;
    let models = client
        .list_models(pb::ListModelsRequest {})
        .await
        .unwrap()
        .into_inner()
        .models;
    let reduced = models.iter().find(|m| m.name == "reduced-residual-f16").unwrap();
    assert_eq!(reduced.metadata["basis.modes"], "12");
    assert_eq!(reduced.metadata["basis.precision"], "f16");
    assert_eq!(reduced.metadata["inputs"], "[interaction]");
    let mesh = server.engine.mesh().clone();
    let response = client
        .predict(pb::PredictRequest {
            model: "reduced-residual".into(),
            grasps: two_graspers(&mesh).iter().map(nak::wire::grasp_message).collect(),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    let t = response.timing.unwrap();
    assert!(t.prior_us > 0.0 && t.network_us > 0.0, "{t:?}");
    assert_eq!(response.interaction_points, 20);
    server.stop().await;
}

/// With the clouds on a GPU (lavapipe in CI), a reduced model uploads its basis and evaluates prior and
/// residual in one dispatch; the field equals the CPU path's to 1e-5 of its size (f32 sums in another
/// order), for every node and for the surface, f32 and f16 bases alike.
#[test]
fn on_the_gpu_prior_and_residual_in_one_dispatch_equal_the_cpu_path() {
    let cpu = engine_with_models(coarse());
    let mut gpu = engine_with_models(coarse());
    let choice = gpu
        .use_prior_backend(nak::prior::PriorBackend::Gpu)
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(choice.contains("GPU"), "{choice}");
    // A model added after the clouds went to the GPU uploads its basis too.
    let dir = test_models().join("phantom-liver-coarse/reduced-residual");
    let late = Arc::new(OnnxModel::load(&dir, gpu.mesh(), nak::model::LoadContext::default()).unwrap());
    assert!(!late.basis_on_gpu());
    gpu.add_model(late.clone());
    assert!(late.basis_on_gpu(), "the basis was not uploaded");
    for model in ["reduced-residual", "reduced-residual-f16"] {
        for selection in [Selection::All, Selection::Surface] {
            let expected = predict(&cpu, model, selection.clone());
            let request = Request {
                model: model.into(),
                grasps: two_graspers(cpu.mesh()),
                selection,
                ..Default::default()
            };
            let on_gpu = gpu.predict(&request).unwrap();
            let d = max_difference(&on_gpu.displacements, &expected);
            assert!(d <= 1e-5 * largest(&expected), "{model}: {d} of {}", largest(&expected));
            assert!(on_gpu.timing.prior_us > 0.0 && on_gpu.timing.network_us > 0.0);
            // The phases say it ran on the GPU, as one request's dispatch.
            let phases = on_gpu.timing.gpu.unwrap_or_else(|| panic!("{model}: no GPU phases"));
            assert!(phases.batch == 1 && phases.wait_us > 0.0, "{phases:?}");
        }
    }
}
