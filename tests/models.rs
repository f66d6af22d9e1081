//! ONNX models under the model contract: loading, refusals, composition with the prior, failures.
//!
//! Needs ONNX Runtime: ORT_DYLIB_PATH must name libonnxruntime.so.1.31.1 (scripts/test sets it).

mod common;

use std::sync::Arc;

use common::models::{
    coarse, copy_model, engine_with_models, held_by_two_graspers, load_error, ort, predict, test_models, two_graspers,
};
use common::server::TestServer;
use nak::engine::DeformationModel;
use nak::engine::{Engine, Grasp, Limits, Request, Selection};
use nak::fem::{GreenFunctions, Stiffness};
use nak::mesh::PriorParams;
use nak::model::GreenModel;
use nak::model::{self, LoadContext, OnnxModel};
use nak::prior::{InteractionPoints, Kelvinlet, NodeCloud, Workspace};
use nak::proto::v1 as pb;
use tonic::Code;

#[test]
fn every_test_model_loads_and_is_listed_with_its_manifest() {
    let engine = engine_with_models(coarse());
    let names: Vec<String> = engine.models().map(|m| m.name.clone()).collect();
    assert_eq!(
        names,
        [
            "kelvinlet",
            "mlp-direct-prior",
            "mlp-residual",
            "pointnet-direct",
            "pointnet-residual",
            "reduced-folded",
            "reduced-forces",
            "reduced-geometry",
            "reduced-residual",
            "reduced-residual-f16"
        ]
    );
    let mlp = engine.models().find(|m| m.name == "mlp-residual").unwrap();
    assert_eq!(mlp.regime, "linear");
    assert_eq!(mlp.metadata["mode"], "residual");
    assert_eq!(mlp.metadata["provenance.made_by"], "tests/models/make_models.py");
}

#[test]
fn residual_models_serve_prior_plus_network_and_direct_models_do_not() {
    let engine = engine_with_models(coarse());
    let prior = predict(&engine, "kelvinlet", Selection::All);
    let residual = predict(&engine, "pointnet-residual", Selection::All);
    let direct = predict(&engine, "pointnet-direct", Selection::All);
    // The residual networks add millimetres to a prior of centimetres.
    let diff: f32 = residual
        .iter()
        .zip(&prior)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max);
    assert!(diff > 1e-5 && diff < 0.02, "{diff}");
    // Held nodes answer the grasp's centimetres whatever the model (the next test).
    let held = held_by_two_graspers(engine.mesh());
    let largest = direct
        .chunks_exact(3)
        .enumerate()
        .filter(|(node, _)| !held.contains(&(*node as u32)))
        .flat_map(|(_, row)| row)
        .fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(
        largest < 0.02,
        "direct output should be the network's small field, got {largest}"
    );
}

#[test]
fn selections_are_rows_of_the_full_field_for_networks_too() {
    let engine = engine_with_models(coarse());
    for model in ["mlp-residual", "mlp-direct-prior", "pointnet-direct"] {
        let full = predict(&engine, model, Selection::All);
        let nodes = vec![3u32, 2000, 17, 3];
        let rows = predict(&engine, model, Selection::List(nodes.clone()));
        for (i, &n) in nodes.iter().enumerate() {
            for k in 0..3 {
                let (a, b) = (rows[3 * i + k], full[3 * n as usize + k]);
                assert!(
                    (a - b).abs() <= 1e-6 * b.abs().max(1e-3),
                    "{model} node {n}: {a} vs {b}"
                );
            }
        }
    }
}

/// A grasper moves the nodes it holds by exactly the grasp's displacement, whatever the model: every
/// test network (full-field, residual, reduced) and the Kelvinlet answer it at the held nodes, on every
/// selection (the random test networks miss it by centimetres on their own).
#[test]
fn held_nodes_answer_their_prescribed_displacement_whatever_the_model() {
    let engine = engine_with_models(coarse());
    let mesh = engine.mesh().clone();
    let held: Vec<(u32, [f32; 3])> = two_graspers(&mesh)
        .into_iter()
        .flat_map(|g| g.nodes.into_iter().map(move |n| (n, g.displacement.map(|v| v as f32))))
        .collect();
    let prescribed = |node: u32| held.iter().find(|&&(n, _)| n == node).map(|&(_, u)| u);
    let row = |field: &[f32], r: usize| -> [f32; 3] { [field[3 * r], field[3 * r + 1], field[3 * r + 2]] };
    let listed = vec![held[3].0, 3, held[0].0, held[3].0, 2000];
    let names: Vec<String> = engine.models().map(|m| m.name.clone()).collect();
    for model in &names {
        let full = predict(&engine, model, Selection::All);
        let surface = predict(&engine, model, Selection::Surface);
        let rows = predict(&engine, model, Selection::List(listed.clone()));
        for &(node, u) in &held {
            assert_eq!(row(&full, node as usize), u, "{model}, every node: held node {node}");
            let on_surface = mesh.surface_nodes.iter().position(|&s| s == node).unwrap();
            assert_eq!(row(&surface, on_surface), u, "{model}, the surface: held node {node}");
        }
        for (r, &node) in listed.iter().enumerate() {
            match prescribed(node) {
                Some(u) => assert_eq!(row(&rows, r), u, "{model}, listed held node {node} (row {r})"),
                // Another node is the model's own answer, as in the full field to f32 rounding.
                None => {
                    let (got, whole) = (row(&rows, r), row(&full, node as usize));
                    for k in 0..3 {
                        assert!(
                            (got[k] - whole[k]).abs() <= 1e-6 * whole[k].abs().max(1e-3),
                            "{model}, listed node {node} (row {r}): {got:?} vs {whole:?}"
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn requests_do_not_leak_into_each_other_through_pooled_buffers() {
    let engine = engine_with_models(coarse());
    let first = predict(&engine, "pointnet-direct", Selection::All);
    // A request grasping elsewhere, then the first again: the pooled feature buffer must be clean.
    let other = Request {
        model: "pointnet-direct".into(),
        grasps: vec![Grasp {
            nodes: engine.mesh().node_sets["grasp_10"].clone(),
            displacement: [0.0, 0.05, 0.0],
            ..Default::default()
        }],
        ..Default::default()
    };
    engine.predict(&other).unwrap();
    assert_eq!(predict(&engine, "pointnet-direct", Selection::All), first);
}

#[test]
fn refuses_a_missing_or_corrupt_model_file() {
    let (_root, dir) = copy_model("mlp-residual");
    std::fs::remove_file(dir.join("model.onnx")).unwrap();
    let err = load_error(&dir);
    assert!(err.contains("model.onnx") && err.contains("No such file"), "{err}");

    let (_root, dir) = copy_model("mlp-residual");
    let bytes = std::fs::read(dir.join("model.onnx")).unwrap();
    std::fs::write(dir.join("model.onnx"), &bytes[..bytes.len() / 2]).unwrap();
    let err = load_error(&dir);
    assert!(err.contains("model.onnx: ONNX Runtime cannot load it"), "{err}");
}

#[test]
fn refuses_wrong_input_or_output_names_and_shapes() {
    let faulty = test_models().join("faulty");
    let err = load_error(&faulty.join("wrong-input-name/wrong-input-name"));
    assert!(
        err.contains("the input is named \"x\"; the model contract names it \"features\""),
        "{err}"
    );
    let err = load_error(&faulty.join("wrong-output-shape/wrong-output-shape"));
    assert!(
        err.contains("output \"displacement\"") && err.contains("[-1, -1, 4]"),
        "{err}"
    );
    // The manifest says the model reads the prior, the graph takes 7 channels.
    let (_root, dir) = copy_model("mlp-residual");
    let manifest = std::fs::read_to_string(dir.join("manifest.toml")).unwrap();
    std::fs::write(
        dir.join("manifest.toml"),
        manifest.replace(r#""active"]"#, r#""active", "prior"]"#),
    )
    .unwrap();
    let err = load_error(&dir);
    assert!(err.contains("input \"features\"") && err.contains("10]"), "{err}");
}

#[test]
fn refuses_a_model_for_another_mesh_or_a_broken_manifest() {
    let (_root, dir) = copy_model("mlp-residual");
    let manifest = std::fs::read_to_string(dir.join("manifest.toml")).unwrap();
    let n = coarse().node_count();
    let refused = |text: String| {
        std::fs::write(dir.join("manifest.toml"), text).unwrap();
        load_error(&dir)
    };
    let err = refused(manifest.replace(&format!("node_count = {n}"), "node_count = 9701"));
    assert!(err.contains("made for a mesh of 9701 nodes"), "{err}");

    let hash = coarse().content_hash.clone();
    let err = refused(manifest.replace(&hash, &"0".repeat(64)));
    assert!(err.contains("made for mesh phantom-liver (0000"), "{err}");

    let err = refused(manifest.replace("mode = \"residual\"", "mode = \"both\""));
    assert!(
        err.contains("manifest.toml") && err.contains("unknown variant `both`"),
        "{err}"
    );

    // A residual network is served as prior + output: Method 2 (reg) is a direct model.
    let err = refused(manifest.replace("method = \"res\"", "method = \"reg\""));
    assert!(err.contains("model.method = Reg is served in mode Direct"), "{err}");

    let err = refused(manifest.replace("epsilon_m = 0.05", "epsilon_m = -0.02"));
    assert!(err.contains("expected 0 < poisson_ratio < 0.5, epsilon_m > 0"), "{err}");
}

/// A network is served with the prior it was trained with, whatever the mesh's prior is: the same
/// graph under a manifest with ε = 3 cm moves by exactly the difference of the two Kelvinlet fields.
#[test]
fn each_model_is_served_with_its_own_prior() {
    let mesh = coarse();
    let (_root, dir) = copy_model("mlp-residual");
    let manifest = std::fs::read_to_string(dir.join("manifest.toml")).unwrap();
    std::fs::write(
        dir.join("manifest.toml"),
        manifest
            .replace("epsilon_m = 0.05", "epsilon_m = 0.03")
            .replace("name = \"mlp-residual\"", "name = \"mlp-residual-eps3\""),
    )
    .unwrap();
    let mut engine = engine_with_models(mesh.clone());
    let own = OnnxModel::load(&dir, &mesh, ort()).unwrap();
    assert_eq!(own.info().metadata["prior.epsilon_m"], "0.03");
    engine.add_model(Arc::new(own));
    let at_3cm = predict(&engine, "mlp-residual-eps3", Selection::All);
    let at_5cm = predict(&engine, "mlp-residual", Selection::All);

    let kelvinlet = |epsilon: f64| {
        let prior = Kelvinlet::new(PriorParams {
            epsilon,
            ..mesh.config.prior
        });
        let mut points = InteractionPoints::default();
        for g in two_graspers(&mesh) {
            for &n in &g.nodes {
                points.push(n, mesh.positions[n as usize], g.displacement);
            }
        }
        let mut workspace = Workspace::default();
        prior.solve(&points, &mut workspace).unwrap();
        let mut field = vec![0.0f32; 3 * mesh.node_count()];
        prior.evaluate(
            &workspace.coefficients,
            &NodeCloud::new(mesh.positions.iter().copied()),
            &mut field,
        );
        field
    };
    let (k3, k5) = (kelvinlet(0.03), kelvinlet(0.05));
    let scale = k5.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    // Held nodes answer the grasp whatever the prior (held_nodes_answer_their_prescribed_displacement…).
    let held = held_by_two_graspers(&mesh);
    for i in (0..at_3cm.len()).filter(|i| !held.contains(&((i / 3) as u32))) {
        let expected = at_5cm[i] - k5[i] + k3[i];
        assert!(
            (at_3cm[i] - expected).abs() <= 1e-5 * scale,
            "row {}: {} vs {expected}",
            i / 3,
            at_3cm[i]
        );
    }
}

#[test]
fn a_model_on_the_green_linear_prior_serves_green_linear_plus_its_network() {
    let mesh = coarse();
    let cache = tempfile::tempdir().unwrap();
    let green = Arc::new(GreenFunctions::load_or_compute(&mesh, Stiffness::Linear, cache.path(), |_, _| {}).unwrap());
    let mut engine = engine_with_models(mesh.clone());
    engine.add_model(Arc::new(GreenModel::new(&mesh, green.clone())));
    let source = |_| Ok(green.clone());
    let on_green = LoadContext {
        ort_dylib: ort(),
        green: Some(&source),
    };
    let mut copies = Vec::new();
    // Both serving paths: a features network (mlp) and an interaction network over a basis.
    for name in ["mlp-residual", "reduced-residual"] {
        let (root, dir) = copy_model(name);
        let manifest = std::fs::read_to_string(dir.join("manifest.toml")).unwrap();
        let renamed = manifest
            .replace("[prior]\n", "[prior]\nmodel = \"green-linear\"\n")
            .replace(&format!("name = \"{name}\""), &format!("name = \"{name}-gl\""));
        std::fs::write(dir.join("manifest.toml"), renamed).unwrap();
        let refused = load_error(&dir);
        assert!(refused.contains("prior.model = \"green-linear\""), "{refused}");
        let model = OnnxModel::load(&dir, &mesh, on_green).unwrap();
        assert_eq!(model.info().metadata["prior.model"], "green-linear");
        engine.add_model(Arc::new(model));
        copies.push(root);
    }
    let some_nodes: Vec<u32> = (0..mesh.node_count() as u32).step_by(7).collect();
    for selection in [Selection::All, Selection::List(some_nodes)] {
        let green_field = predict(&engine, "green-linear", selection.clone());
        let kelvinlet = predict(&engine, "kelvinlet", selection.clone());
        let scale = green_field.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        for name in ["mlp-residual", "reduced-residual"] {
            // The network's share is the same whichever prior it is added to.
            let on_kelvinlet = predict(&engine, name, selection.clone());
            let on_green = predict(&engine, &format!("{name}-gl"), selection.clone());
            for i in 0..on_green.len() {
                let expected = green_field[i] + on_kelvinlet[i] - kelvinlet[i];
                assert!(
                    (on_green[i] - expected).abs() <= 1e-5 * scale,
                    "{name}, value {i}: {} vs {expected}",
                    on_green[i]
                );
            }
        }
    }
}

#[tokio::test]
async fn a_model_failing_at_run_time_answers_internal_and_the_server_goes_on() {
    let mesh = coarse();
    let mut engine = Engine::new(mesh.clone(), Limits::default());
    let faulty = test_models().join("faulty/fails-at-run-time");
    for m in model::load_all(&faulty, &mesh, ort()).unwrap() {
        engine.add_model(Arc::new(m));
    }
    let server = TestServer::with_engine(engine, 1 << 20).await;
    let mut client = server.client().await;
    let grasps: Vec<pb::Grasp> = two_graspers(&mesh).iter().map(nak::wire::grasp_message).collect();
    let request = |model: &str| pb::PredictRequest {
        model: model.into(),
        grasps: grasps.clone(),
        ..Default::default()
    };
    let status = client.predict(request("fails-at-run-time")).await.unwrap_err();
    assert_eq!(status.code(), Code::Internal);
    assert!(
        status.message().contains("fails-at-run-time failed") && status.message().contains("Gather"),
        "{status:?}"
    );
    assert!(client.predict(request("kelvinlet")).await.is_ok());
    // The failed model itself is still there for the next request (and fails the same way).
    assert_eq!(
        client.predict(request("fails-at-run-time")).await.unwrap_err().code(),
        Code::Internal
    );
    server.stop().await;
}

#[tokio::test]
async fn timing_reports_prior_network_and_total() {
    let server = TestServer::with_engine(engine_with_models(coarse()), 1 << 20).await;
    let mut client = server.client().await;
    let mesh = server.engine.mesh().clone();
    let nodes: Vec<u32> = mesh.node_sets["grasp_04"].iter().take(10).copied().collect();
    let response = client
        .predict(pb::PredictRequest {
            model: "mlp-residual".into(),
            grasps: vec![pb::Grasp {
                nodes,
                displacement: Some(pb::Vec3 {
                    x: 0.0,
                    y: 0.02,
                    z: 0.0,
                }),
                ..Default::default()
            }],
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    let t = response.timing.unwrap();
    assert!(t.prior_us > 0.0 && t.network_us > 0.0, "{t:?}");
    assert!(t.total_us >= t.network_us && t.total_us >= t.prior_us, "{t:?}");
    assert_eq!(response.model, "mlp-residual");
    server.stop().await;
}
