//! The ONNX test models (tests/models/make_models.py) on the coarse phantom, and ways to break them.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use nak::engine::{Engine, Grasp, Limits, Request, Selection};
use nak::mesh::{self, MeshSource, TetMesh};
use nak::model::{self, OnnxModel};

pub fn coarse() -> Arc<TetMesh> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver/liver-coarse.msh");
    Arc::new(mesh::load(&MeshSource::File(path)).unwrap())
}

pub fn test_models() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/models")
}

pub fn ort() -> Option<&'static Path> {
    assert!(
        std::env::var_os("ORT_DYLIB_PATH").is_some(),
        "ORT_DYLIB_PATH is not set: run scripts/test, or export ORT_DYLIB_PATH=$(scripts/onnxruntime-path)"
    );
    None
}

pub fn engine_with_models(mesh: Arc<TetMesh>) -> Engine {
    let mut engine = Engine::new(mesh.clone(), Limits::default());
    for m in model::load_all(&test_models().join("phantom-liver-coarse"), &mesh, ort()).unwrap() {
        engine.add_model(Arc::new(m));
    }
    engine
}

pub fn two_graspers(mesh: &TetMesh) -> Vec<Grasp> {
    let grasp = |set: &str, u: [f64; 3]| Grasp {
        nodes: mesh.node_sets[set].iter().take(10).copied().collect(),
        displacement: u,
        ..Default::default()
    };
    vec![
        grasp("grasp_03", [0.01, 0.03, -0.01]),
        grasp("grasp_08", [-0.02, 0.02, 0.015]),
    ]
}

/// The nodes `two_graspers` hold, whose rows every model answers with the grasp's displacement.
pub fn held_by_two_graspers(mesh: &TetMesh) -> Vec<u32> {
    two_graspers(mesh).into_iter().flat_map(|g| g.nodes).collect()
}

pub fn predict(engine: &Engine, model: &str, selection: Selection) -> Vec<f32> {
    let request = Request {
        model: model.into(),
        grasps: two_graspers(engine.mesh()),
        selection,
        ..Default::default()
    };
    engine.predict(&request).unwrap().displacements
}

/// A copy of a test model in a fresh directory, to break one thing in it.
pub fn copy_model(name: &str) -> (tempfile::TempDir, PathBuf) {
    let root = tempfile::tempdir().unwrap();
    let dir = root.path().join(name);
    std::fs::create_dir(&dir).unwrap();
    let source = test_models().join("phantom-liver-coarse").join(name);
    for file in ["manifest.toml", "model.onnx", "basis.safetensors"] {
        if source.join(file).exists() {
            std::fs::copy(source.join(file), dir.join(file)).unwrap();
        }
    }
    (root, dir)
}

pub fn load_error(dir: &Path) -> String {
    match OnnxModel::load(dir, &coarse(), ort()) {
        Ok(_) => panic!("{} was accepted", dir.display()),
        Err(e) => e.to_string(),
    }
}
