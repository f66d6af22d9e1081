//! Grasp forces end to end: over gRPC per model (exact, estimate, learned, none), and in datasets.

mod common;

use std::path::Path;
use std::sync::Arc;

use common::models::{coarse, copy_model, engine_with_models, load_error, ort, test_models, two_graspers};
use common::server::TestServer;
use nak::data::dataset;
use nak::engine::{DeformationModel, Grasp};
use nak::fem::{GreenFunctions, Stiffness, nodal_forces, solve_dirichlet};
use nak::model::{GreenModel, LoadContext, OnnxModel};
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

type Client = nak::proto::v1::deformation_client::DeformationClient<tonic::transport::Channel>;

/// What ListModels says of the forces of `model`.
async fn listed_forces(client: &mut Client, model: &str) -> i32 {
    let listed = client.list_models(pb::ListModelsRequest {}).await.unwrap().into_inner();
    listed.models.iter().find(|m| m.name == model).unwrap().forces
}

/// `model`'s answer to `grasps` over gRPC.
async fn answer(client: &Client, model: &str, grasps: &[Grasp]) -> pb::PredictResponse {
    let request = pb::PredictRequest {
        model: model.into(),
        grasps: grasps.iter().map(grasp_message).collect(),
        ..Default::default()
    };
    client.clone().predict(request).await.unwrap().into_inner()
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
        .find(|&&n| !green.candidates().contains(&n) && !mesh.is_fixed(n))
        .unwrap();
    engine.add_model(Arc::new(GreenModel::new(&mesh, Arc::new(green))));
    let server = TestServer::with_engine(engine, 1 << 20).await;
    let mut client = server.client().await;
    assert_eq!(
        listed_forces(&mut client, "green-linear").await,
        pb::Forces::Exact as i32
    );
    assert_eq!(
        listed_forces(&mut client, "kelvinlet").await,
        pb::Forces::Estimate as i32
    );
    assert_eq!(
        listed_forces(&mut client, "mlp-residual").await,
        pb::Forces::Unavailable as i32
    );

    let grasps = two_graspers(&mesh);
    let truth = fem_grasp_forces(&mesh, &grasps);
    // green-linear: the FEM's forces, to f32 on the wire.
    let exact = answer(&client, "green-linear", &grasps).await.grasp_forces;
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
    let estimate = answer(&client, "kelvinlet", &grasps).await.grasp_forces;
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
    assert!(answer(&client, "mlp-residual", &grasps).await.grasp_forces.is_empty());
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

/// tests/models/make_models.py's FORCE_GAINS: reduced-forces gives each point FORCE_GAINS ⊙ u_k.
const FORCE_GAINS: [f64; 3] = [100.0, 200.0, 300.0];

fn assert_close(served: &[[f64; 3]], expected: &[[f64; 3]], what: &str) {
    assert_eq!(served.len(), expected.len(), "{what}");
    for (s, e) in served.iter().zip(expected) {
        let size = e.iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!(size > 0.0, "{what}: nothing to compare");
        for k in 0..3 {
            assert!((s[k] - e[k]).abs() <= 1e-5 * size, "{what}: {s:?} against {e:?}");
        }
    }
}

#[tokio::test]
async fn a_network_with_a_forces_output_serves_each_grasps_sum_direct_or_on_its_priors_forces() {
    let mesh = coarse();
    let cache = tempfile::tempdir().unwrap();
    let mut engine = engine_with_models(mesh.clone());
    let green = Arc::new(GreenFunctions::load_or_compute(&mesh, Stiffness::Linear, cache.path(), |_, _| {}).unwrap());
    engine.add_model(Arc::new(GreenModel::new(&mesh, green.clone())));
    // The same graph on green-linear, its forces added to green-linear's own.
    let (_root, dir) = copy_model("reduced-forces");
    let manifest = std::fs::read_to_string(dir.join("manifest.toml")).unwrap();
    std::fs::write(
        dir.join("manifest.toml"),
        manifest
            .replace("[prior]\n", "[prior]\nmodel = \"green-linear\"\n")
            .replace("name = \"reduced-forces\"", "name = \"reduced-forces-gl\"")
            .replace(
                "mode = \"direct\"\n",
                "mode = \"residual\"\nmean_relative_error = 0.25\n",
            ),
    )
    .unwrap();
    let source = |_| Ok(green.clone());
    let context = LoadContext {
        ort_dylib: ort(),
        green: Some(&source),
    };
    let on_green = OnnxModel::load(&dir, &mesh, context).unwrap();
    assert_eq!(on_green.info().metadata["forces.mean_relative_error"], "0.25");
    engine.add_model(Arc::new(on_green));
    let server = TestServer::with_engine(engine, 1 << 20).await;
    let mut client = server.client().await;
    let learned_forces = pb::Forces::Learned as i32;
    assert_eq!(listed_forces(&mut client, "reduced-forces").await, learned_forces);
    assert_eq!(listed_forces(&mut client, "reduced-forces-gl").await, learned_forces);
    assert_eq!(
        listed_forces(&mut client, "reduced-residual").await,
        pb::Forces::Unavailable as i32
    );

    let grasps = two_graspers(&mesh);
    let vectors = |forces: &[pb::Vec3]| -> Vec<[f64; 3]> {
        forces.iter().map(|f| [f.x as f64, f.y as f64, f.z as f64]).collect()
    };
    // Each grasp holds its nodes at one displacement: the sum over them is n_g FORCE_GAINS ⊙ u_g.
    let learned: Vec<[f64; 3]> = grasps
        .iter()
        .map(|g| std::array::from_fn(|k| g.nodes.len() as f64 * FORCE_GAINS[k] * g.displacement[k]))
        .collect();
    let direct = answer(&client, "reduced-forces", &grasps).await;
    assert_close(&vectors(&direct.grasp_forces), &learned, "direct");
    // A forces output leaves the field as it was.
    let field = answer(&client, "reduced-residual", &grasps).await.displacements;
    assert_eq!(direct.displacements, field);
    let prior = vectors(&answer(&client, "green-linear", &grasps).await.grasp_forces);
    let residual: Vec<[f64; 3]> = prior
        .iter()
        .zip(&learned)
        .map(|(p, l)| std::array::from_fn(|k| p[k] + l[k]))
        .collect();
    assert_close(
        &vectors(&answer(&client, "reduced-forces-gl", &grasps).await.grasp_forces),
        &residual,
        "residual",
    );
    server.stop().await;
}

/// tests/models/make_models.py's GEOMETRY_GAIN: reduced-geometry gives each point GEOMETRY_GAIN · V_k n_k
/// from the normal and nodal volume nak feeds it.
const GEOMETRY_GAIN: f64 = 1e6;

#[tokio::test]
async fn a_graph_that_reads_surface_geometry_is_fed_each_points_normal_and_nodal_volume() {
    let mesh = coarse();
    let server = TestServer::with_engine(engine_with_models(mesh.clone()), 1 << 20).await;
    let client = server.client().await;
    let grasps = two_graspers(&mesh);
    let expected: Vec<[f64; 3]> = grasps
        .iter()
        .map(|g| {
            std::array::from_fn(|k| {
                g.nodes
                    .iter()
                    .map(|&n| GEOMETRY_GAIN * mesh.nodal_volumes[n as usize] * mesh.normals[n as usize][k])
                    .sum()
            })
        })
        .collect();
    let served = answer(&client, "reduced-geometry", &grasps).await;
    let served: Vec<[f64; 3]> = served
        .grasp_forces
        .iter()
        .map(|f| [f.x as f64, f.y as f64, f.z as f64])
        .collect();
    assert_close(&served, &expected, "geometry");
    server.stop().await;
}

#[test]
fn a_forces_output_of_the_wrong_shape_or_without_its_manifest_section_is_refused_at_load() {
    let faulty = test_models().join("faulty");
    let err = load_error(&faulty.join("forces-two-axes/forces-two-axes"));
    assert!(
        err.contains("\"forces\"") && err.contains("[batch, K, 3]") && err.contains("2]"),
        "{err}"
    );
    let err = load_error(&faulty.join("forces-per-set/forces-per-set"));
    assert!(err.contains("\"forces\"") && err.contains("[batch, K, 3]"), "{err}");
    let (_root, dir) = copy_model("reduced-forces");
    let manifest = std::fs::read_to_string(dir.join("manifest.toml")).unwrap();
    let edit = |text: String| std::fs::write(dir.join("manifest.toml"), text).unwrap();
    edit(manifest.replace("[forces]\nmode = \"direct\"\n", ""));
    let err = load_error(&dir);
    assert!(
        err.contains("gives \"forces\"") && err.contains("no [forces] section"),
        "{err}"
    );
    // Residual forces need a prior that has forces of its own to add them to.
    edit(manifest.replace("mode = \"direct\"\n", "mode = \"residual\"\n"));
    let err = load_error(&dir);
    assert!(
        err.contains("forces.mode = \"residual\"") && err.contains("Kelvinlet"),
        "{err}"
    );
    let (_other, plain) = copy_model("reduced-residual");
    let manifest = std::fs::read_to_string(plain.join("manifest.toml")).unwrap();
    std::fs::write(
        plain.join("manifest.toml"),
        manifest + "\n[forces]\nmode = \"direct\"\n",
    )
    .unwrap();
    let err = load_error(&plain);
    assert!(
        err.contains("no \"forces\" output") && err.contains("has a [forces] section"),
        "{err}"
    );
}
