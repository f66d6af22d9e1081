//! `nak organ new`: a surface written by the test, meshed and labelled, its Green's functions cached,
//! a small network trained on its linear data and scored on another seed, and all of it served:
//! green-linear over gRPC equals the linear finite-element solve on the made mesh, and the network
//! answers. The meshing and training stages run the `nak_organ` and `nak_training` packages with the
//! project's `.venv` (scripts/setup-python --training).

mod common;

use std::f64::consts::PI;
use std::path::{Path, PathBuf};
use std::process::Output;

use common::process::{ServeProcess, nak};
use nak::fem::solve_dirichlet;
use nak::mesh::{self, MeshSource};
use nak::proto::v1::deformation_client::DeformationClient;
use nak::proto::v1::{Grasp, ListModelsRequest, PredictRequest, Vec3};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// An ellipsoid of semi-axes 40, 30 and 25 mm: a latitude–longitude net, closed at its poles, its
/// triangles facing out. `leave_out` drops one triangle (an open surface).
fn ellipsoid(leave_out: Option<usize>) -> Vec<[[f64; 3]; 3]> {
    let (rings, segments) = (12, 24);
    let point = |i: usize, j: usize| -> [f64; 3] {
        let (theta, phi) = (
            PI * i as f64 / rings as f64,
            2.0 * PI * (j % segments) as f64 / segments as f64,
        );
        let (s, z) = match i {
            0 => (0.0, 25.0),
            i if i == rings => (0.0, -25.0),
            _ => (theta.sin(), 25.0 * theta.cos()),
        };
        [40.0 * s * phi.cos(), 30.0 * s * phi.sin(), z]
    };
    let mut triangles = Vec::new();
    for i in 0..rings {
        for j in 0..segments {
            let (a, b, c, d) = (point(i, j), point(i + 1, j), point(i + 1, j + 1), point(i, j + 1));
            if i + 1 < rings {
                triangles.push([a, b, c]);
            }
            if i > 0 {
                triangles.push([a, c, d]);
            }
        }
    }
    if let Some(k) = leave_out {
        triangles.remove(k);
    }
    triangles
}

/// A coordinate to the micrometre, with no negative zeros, so that shared corners read as one vertex.
fn number(v: f64) -> String {
    format!("{:.6}", (v * 1e6).round() / 1e6 + 0.0)
}

/// The ellipsoid as an ASCII STL (mm).
fn ellipsoid_stl(path: &Path, leave_out: Option<usize>) {
    let mut stl = String::from("solid ellipsoid\n");
    for t in ellipsoid(leave_out) {
        stl.push_str("  facet normal 0 0 0\n    outer loop\n");
        for p in t {
            stl.push_str(&format!(
                "      vertex {} {} {}\n",
                number(p[0]),
                number(p[1]),
                number(p[2])
            ));
        }
        stl.push_str("    endloop\n  endfacet\n");
    }
    stl.push_str("endsolid ellipsoid\n");
    std::fs::write(path, stl).unwrap();
}

/// The ellipsoid as a Wavefront OBJ (mm): each corner once, faces by 1-based vertex index.
fn ellipsoid_obj(path: &Path) {
    let (mut vertices, mut faces) = (Vec::<String>::new(), String::new());
    for t in ellipsoid(None) {
        let mut face = String::from("f");
        for p in t {
            let v = format!("{} {} {}", number(p[0]), number(p[1]), number(p[2]));
            let index = vertices.iter().position(|w| *w == v).unwrap_or_else(|| {
                vertices.push(v);
                vertices.len() - 1
            });
            face.push_str(&format!(" {}", index + 1));
        }
        faces.push_str(&face);
        faces.push('\n');
    }
    let obj: String = vertices.iter().map(|v| format!("v {v}\n")).collect();
    std::fs::write(path, obj + &faces).unwrap();
}

/// The coarse setting: 500 nodes, three grasp regions, a network of 300 steps on 200 samples.
fn organ_new(surface: &Path, out: &Path, cache: &Path) -> Output {
    organ_new_with(
        surface,
        out,
        cache,
        &["--samples", "200", "--held-out", "60", "--steps", "300"],
    )
}

fn organ_new_with(surface: &Path, out: &Path, cache: &Path, options: &[&str]) -> Output {
    nak()
        .current_dir(repo())
        .args(["organ", "new"])
        .arg(surface)
        .args(["--units", "mm", "--fixed", "sphere:0,0,-25,12", "--grasp-regions", "3"])
        .args(["--target-nodes", "500"])
        .args(options)
        .arg("--out")
        .arg(out)
        .arg("--cache-dir")
        .arg(cache)
        .output()
        .unwrap()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

#[test]
fn a_surface_becomes_a_served_organ_whose_green_linear_is_the_linear_fem_solve() {
    let dir = tempfile::tempdir().unwrap();
    let (surface, out, cache) = (
        dir.path().join("ellipsoid.stl"),
        dir.path().join("organ"),
        dir.path().join("cache"),
    );
    ellipsoid_stl(&surface, None);
    let made = organ_new(&surface, &out, &cache);
    let said = text(&made.stdout);
    assert!(made.status.success(), "{said}\n{}", text(&made.stderr));
    for stage in [
        "[1/6] mesh: made",
        "[2/6] green-linear",
        "[3/6] green-tangent",
        "serves the exact models",
        "[4/6] data",
        "[5/6] network",
        "(ONNX Runtime checked against PyTorch)",
        "[6/6] score: DCM",
        "on 60 held-out samples of seed 1",
        "is ready",
    ] {
        assert!(said.contains(stage), "{stage}: {said}");
    }
    let manifest = std::fs::read_to_string(out.join("pod-res/manifest.toml")).unwrap();
    assert!(
        manifest.contains("split = \"all\"") && manifest.contains("scored_on_seed = 1"),
        "{manifest}"
    );
    // Run again, nothing changed: nothing is made again.
    let again = organ_new(&surface, &out, &cache);
    let said = text(&again.stdout);
    assert!(again.status.success(), "{said}\n{}", text(&again.stderr));
    for skipped in ["mesh: ", "network: "] {
        assert!(
            said.contains(&format!("{skipped}{}", out.display())) && said.contains("up to date"),
            "{said}"
        );
    }
    assert_eq!(said.matches("already cached").count(), 2, "{said}");
    assert!(!said.contains("trained and exported"), "{said}");

    let mut serve = nak();
    serve
        .args(["serve", "--green-linear", "--green-tangent", "--mesh"])
        .arg(&out)
        .arg("--cache-dir")
        .arg(&cache);
    let server = ServeProcess::start(serve);
    let address = server.address.clone();
    let organ = mesh::load(&MeshSource::Directory(out.clone())).unwrap();
    let held = organ.node_sets["grasp_01"][0];
    let pull = [0.0, 0.004, 0.002];
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let (models, field, network) = runtime.block_on(async {
        let mut client = DeformationClient::connect(format!("http://{address}")).await.unwrap();
        let models = client
            .list_models(ListModelsRequest {})
            .await
            .unwrap()
            .into_inner()
            .models;
        let mut answer = async |model: &str| -> Vec<f64> {
            let request = PredictRequest {
                model: model.into(),
                grasps: vec![Grasp {
                    nodes: vec![held],
                    displacement: Some(Vec3 {
                        x: pull[0] as f32,
                        y: pull[1] as f32,
                        z: pull[2] as f32,
                    }),
                    ..Default::default()
                }],
                ..Default::default()
            };
            let answer = client.predict(request).await.unwrap().into_inner();
            answer
                .displacements
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64)
                .collect()
        };
        let field = answer("green-linear").await;
        let network = answer("pod-res").await;
        (models, field, network)
    });
    let names: Vec<&str> = models.iter().map(|m| m.name.as_str()).collect();
    for model in ["kelvinlet", "green-linear", "green-tangent", "pod-res"] {
        assert!(names.contains(&model), "{model} not served: {names:?}");
    }
    let direct = solve_dirichlet(&organ, &[(held, pull)]).unwrap();
    let (mut difference, mut norm) = (0.0, 0.0);
    for (served, exact) in field.chunks(3).zip(&direct) {
        for k in 0..3 {
            difference += (served[k] - exact[k]).powi(2);
            norm += exact[k].powi(2);
        }
    }
    // The field travels in f32, and the cached Green's functions are f32.
    let relative = (difference / norm).sqrt();
    assert!(
        relative < 1e-5,
        "green-linear differs from the direct solve by {relative:e}"
    );
    // The network answers every node, finitely, and moves the held node (300 steps cannot make it exact).
    assert_eq!(network.len(), field.len());
    assert!(
        network.iter().all(|v| v.is_finite()),
        "pod-res answered a non-finite field"
    );
    let moved = &network[3 * held as usize..3 * held as usize + 3];
    assert!(
        moved.iter().any(|v| v.abs() > 1e-4),
        "pod-res left the held node at rest: {moved:?}"
    );
    let (exit, log) = server.stop();
    assert!(exit.success(), "{log:?}");
}

#[test]
fn an_obj_surface_becomes_an_organ_whose_exact_models_are_ready_without_a_network() {
    let dir = tempfile::tempdir().unwrap();
    let (surface, out, cache) = (
        dir.path().join("ellipsoid.obj"),
        dir.path().join("organ"),
        dir.path().join("cache"),
    );
    ellipsoid_obj(&surface);
    let made = organ_new_with(&surface, &out, &cache, &["--no-network"]);
    let said = text(&made.stdout);
    assert!(made.status.success(), "{said}\n{}", text(&made.stderr));
    for stage in [
        "[1/3] mesh: made",
        "[2/3] green-linear",
        "[3/3] green-tangent",
        "serves the exact models",
    ] {
        assert!(said.contains(stage), "{stage}: {said}");
    }
    assert!(!said.contains("[4/") && !out.join("data").exists(), "{said}");
    let organ = mesh::load(&MeshSource::Directory(out)).unwrap();
    assert!(
        (400..=600).contains(&organ.node_count()),
        "{} nodes",
        organ.node_count()
    );
    for set in ["fixed", "grasp_01", "grasp_02", "grasp_03"] {
        assert!(!organ.node_sets[set].is_empty(), "{set} is empty");
    }
}

#[test]
fn an_open_surface_is_refused_naming_the_file_and_nothing_is_made() {
    let dir = tempfile::tempdir().unwrap();
    let (surface, out) = (dir.path().join("holed.stl"), dir.path().join("organ"));
    ellipsoid_stl(&surface, Some(100));
    let refused = organ_new(&surface, &out, &dir.path().join("cache"));
    let said = text(&refused.stderr);
    assert!(!refused.status.success(), "{said}");
    assert!(said.contains("holed.stl") && said.contains("open"), "{said}");
    assert!(said.contains("the meshing stage did not make"), "{said}");
    assert!(!out.join("organ.msh").exists());
}
