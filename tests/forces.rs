//! Grasp forces end to end: over gRPC per model (exact, estimate, none), and in datasets.

mod common;

use std::path::Path;
use std::sync::Arc;

use common::models::{coarse, engine_with_models, two_graspers};
use common::server::TestServer;
use nak::data::dataset;
use nak::engine::Grasp;
use nak::fem::{GreenFunctions, Stiffness, nodal_forces, solve_dirichlet};
use nak::model::GreenModel;
use nak::proto::v1 as pb;
use nak::wire::grasp_message;

/// Each grasp's total of the direct FEM solve's K·u at its held nodes.
fn fem_grasp_forces(mesh: &nak::mesh::TetMesh, grasps: &[Grasp]) -> Vec<[f64; 3]> {
    let prescribed: Vec<(u32, [f64; 3])> = grasps
        .iter()
        .flat_map(|g| g.nodes.iter().map(|&n| (n, g.displacement)))
        .collect();
    let u = solve_dirichlet(mesh, &prescribed).unwrap();
    grasps
        .iter()
        .map(|g| {
            let f = nodal_forces(mesh, &u, &g.nodes).unwrap();
            std::array::from_fn(|k| f.iter().map(|v| v[k]).sum())
        })
        .collect()
}

#[tokio::test]
async fn each_model_answers_with_exact_estimated_or_no_forces_and_says_which() {
    let mesh = coarse();
    let cache = tempfile::tempdir().unwrap();
    let mut engine = engine_with_models(mesh.clone());
    let green = GreenFunctions::load_or_compute(&mesh, Stiffness::Linear, cache.path(), |_, _| {}).unwrap();
    let unreached = *mesh
        .surface_nodes
        .iter()
        .find(|n| !green.candidates().contains(n))
        .unwrap();
    engine.add_model(Arc::new(GreenModel::new(&mesh, Arc::new(green))));
    let server = TestServer::with_engine(engine, 1 << 20).await;
    let mut client = server.client().await;
    let listed = client
        .list_models(pb::ListModelsRequest {})
        .await
        .unwrap()
        .into_inner()
        .models;
    let forces_of = |name: &str| listed.iter().find(|m| m.name == name).unwrap().forces;
    assert_eq!(forces_of("green-linear"), pb::Forces::Exact as i32);
    assert_eq!(forces_of("kelvinlet"), pb::Forces::Estimate as i32);
    assert_eq!(forces_of("mlp-residual"), pb::Forces::Unavailable as i32);

    let grasps = two_graspers(&mesh);
    let truth = fem_grasp_forces(&mesh, &grasps);
    let answer = |model: &str| {
        let request = pb::PredictRequest {
            model: model.into(),
            grasps: grasps.iter().map(grasp_message).collect(),
            ..Default::default()
        };
        let mut client = client.clone();
        async move { client.predict(request).await.unwrap().into_inner().grasp_forces }
    };
    // green-linear: the FEM's forces, to f32 on the wire.
    let exact = answer("green-linear").await;
    assert_eq!(exact.len(), 2);
    for (served, truth) in exact.iter().zip(&truth) {
        let served = [served.x as f64, served.y as f64, served.z as f64];
        let size = truth.iter().map(|v| v * v).sum::<f64>().sqrt();
        for k in 0..3 {
            assert!(
                (served[k] - truth[k]).abs() < 1e-5 * size,
                "{served:?} against {truth:?}"
            );
        }
    }
    // The Kelvinlet's estimate: one force per grasp, the library's to f32.
    let estimate = answer("kelvinlet").await;
    let request = nak::engine::Request {
        grasps: grasps.clone(),
        ..Default::default()
    };
    let library = server.engine.predict(&request).unwrap().grasp_forces.unwrap();
    assert_eq!(estimate.len(), 2);
    for (served, library) in estimate.iter().zip(&library) {
        assert_eq!([served.x, served.y, served.z], library.map(|v| v as f32));
    }
    // A network gives none rather than a made-up value.
    assert!(answer("mlp-residual").await.is_empty());
    // green-linear answers only where it has Green's functions, and says so elsewhere.
    let outside = pb::PredictRequest {
        model: "green-linear".into(),
        grasps: vec![pb::Grasp {
            nodes: vec![unreached],
            ..grasp_message(&grasps[0])
        }],
        ..Default::default()
    };
    let refused = client.predict(outside).await.unwrap_err();
    assert_eq!(refused.code(), tonic::Code::InvalidArgument, "{refused:?}");
    assert!(
        refused
            .message()
            .contains(&format!("no Green's function for node {unreached}")),
        "{refused:?}"
    );
    server.stop().await;
}

#[test]
fn datasets_store_each_grasps_fem_force() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("data");
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver/liver-coarse.msh");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_nak"))
        .arg("datagen")
        .arg("--mesh")
        .arg(&path)
        .args([
            "--single",
            "3",
            "--multi",
            "3",
            "--chunk-size",
            "6",
            "--seed",
            "2",
            "--out",
        ])
        .arg(&out)
        .arg("--cache-dir")
        .arg(dir.path().join("cache"))
        .output()
        .unwrap();
    assert!(status.status.success(), "{}", String::from_utf8_lossy(&status.stderr));
    let mesh = coarse();
    let info = dataset::read_info(&out).unwrap();
    let samples = dataset::read_chunk(&out, 0, info.node_count).unwrap();
    assert_eq!(samples.len(), 6);
    for (sample, _) in &samples {
        let stored = sample.forces().expect("every grasp has a force");
        let truth = fem_grasp_forces(&mesh, &sample.grasps());
        for (s, t) in stored.iter().zip(&truth) {
            let size = t.iter().map(|v| v * v).sum::<f64>().sqrt();
            assert!(size > 0.0);
            for k in 0..3 {
                assert!(
                    (s[k] - t[k]).abs() < 1e-6 * size,
                    "sample {}: {s:?} against {t:?}",
                    sample.index
                );
            }
        }
    }
}
