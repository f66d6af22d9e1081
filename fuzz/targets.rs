//! The fuzz targets' bodies, shared by the libFuzzer binaries (`fuzz/fuzz_targets/`, run by
//! `scripts/fuzz`) and the stable regression test (`tests/fuzz_regressions.rs`), which replays every
//! input kept under `fuzz/regressions/<target>/`.
//!
//! Each target feeds untrusted bytes to one reader the server exposes and demands an answer or an
//! error, never a panic; where the reader succeeds, what it returns is checked for the invariants
//! the rest of nak relies on. A target returns whether the input was accepted.

use std::sync::{Arc, OnceLock};

use arbitrary::{Arbitrary, Unstructured};
use nak::engine::{Engine, Limits};
use nak::fem::{GreenFunctions, Stiffness};
use nak::mesh::{MeshConfig, TetMesh};
use nak::model::GreenModel;
use nak::model::Manifest;
use nak::proto::v1 as pb;

/// A target: whether it accepted the input (it panics on a bug).
pub type Target = fn(&[u8]) -> bool;

/// Every target, by the name of its corpus and regressions folder.
pub const TARGETS: [(&str, Target); 5] = [
    ("msh", msh),
    ("mesh_config", mesh_config),
    ("manifest", manifest),
    ("request", request),
    ("replay", replay),
];

fn box_config() -> MeshConfig {
    let text = include_str!("../tests/fixtures/model.toml");
    MeshConfig::parse(text, "model.toml").expect("tests/fixtures/model.toml is valid")
}

/// The box fixture with its configuration: what the manifest and request targets serve.
fn box_mesh() -> &'static Arc<TetMesh> {
    static MESH: OnceLock<Arc<TetMesh>> = OnceLock::new();
    MESH.get_or_init(|| {
        let mesh = TetMesh::from_msh(include_bytes!("../tests/fixtures/box.msh"), "box.msh", box_config())
            .expect("box.msh is valid");
        Arc::new(mesh)
    })
}

/// An MSH file (ASCII or binary) through the parser and every check a mesh passes before serving.
pub fn msh(data: &[u8]) -> bool {
    let Ok(mesh) = TetMesh::from_msh(data, "fuzz.msh", box_config()) else {
        return false;
    };
    let n = mesh.node_count() as u32;
    assert!(
        mesh.tets.iter().flatten().all(|&v| v < n),
        "a tet refers to a missing node"
    );
    assert!(mesh.surface_nodes.iter().all(|&v| v < n), "a surface node is missing");
    assert!(mesh.total_volume() > 0.0, "an accepted mesh has no volume");
    true
}

/// A mesh's `model.toml`.
pub fn mesh_config(data: &[u8]) -> bool {
    std::str::from_utf8(data).is_ok_and(|text| MeshConfig::parse(text, "model.toml").is_ok())
}

/// A model's `manifest.toml`, and its check against the mesh it would serve.
pub fn manifest(data: &[u8]) -> bool {
    let Ok(text) = std::str::from_utf8(data) else {
        return false;
    };
    let Ok(manifest) = Manifest::parse(text, "manifest.toml") else {
        return false;
    };
    // Every accepted manifest is also checked against a mesh (the box is never the one it names).
    let _ = manifest.check_against(box_mesh(), "manifest.toml");
    true
}

/// The engine serving the box: the Kelvinlet and green-linear (its Green's functions computed once,
/// into a folder of the fuzzing process's own).
fn engine() -> &'static Engine {
    static ENGINE: OnceLock<Engine> = OnceLock::new();
    ENGINE.get_or_init(|| {
        let mesh = box_mesh().clone();
        let cache = std::env::temp_dir().join(format!("nak-fuzz-{}", std::process::id()));
        let green = GreenFunctions::load_or_compute(&mesh, Stiffness::Linear, &cache, |_, _| {})
            .expect("green-linear on the box");
        // Few interaction points: the solve grows as (3K)³, and the fuzzer favours large requests,
        // which would spend its time solving instead of exploring; the limit's own check is fuzzed.
        let limits = Limits {
            max_interaction_points: 24,
            ..Limits::default()
        };
        let mut engine = Engine::new(mesh.clone(), limits);
        engine.add_model(Arc::new(GreenModel::new(&mesh, Arc::new(green))));
        engine
    })
}

/// A request as a client could send it, shaped so that the fuzzer reaches validation and compute
/// often: node ids mostly near the mesh's range, any floats (NaN, infinities, subnormals), any
/// selection code and model name.
#[derive(Debug, Arbitrary)]
struct FuzzRequest {
    model: FuzzModel,
    mesh: Option<String>,
    selection: i32,
    nodes: Vec<u32>,
    grasps: Vec<FuzzGrasp>,
}

#[derive(Debug, Arbitrary)]
enum FuzzModel {
    Default,
    Kelvinlet,
    GreenLinear,
    Named(String),
}

#[derive(Debug, Arbitrary)]
struct FuzzGrasp {
    nodes: Vec<u16>,
    point: Option<[f32; 3]>,
    radius: f32,
    displacement: Option<[f32; 3]>,
}

fn vec3([x, y, z]: [f32; 3]) -> pb::Vec3 {
    pb::Vec3 { x, y, z }
}

impl FuzzRequest {
    fn message(self) -> pb::PredictRequest {
        pb::PredictRequest {
            model: match self.model {
                FuzzModel::Default => String::new(),
                FuzzModel::Kelvinlet => "kelvinlet".into(),
                FuzzModel::GreenLinear => "green-linear".into(),
                FuzzModel::Named(name) => name,
            },
            mesh: self.mesh.unwrap_or_default(),
            selection: self.selection,
            nodes: self.nodes,
            grasps: self
                .grasps
                .into_iter()
                .map(|g| pb::Grasp {
                    nodes: g.nodes.into_iter().map(u32::from).collect(),
                    point: g.point.map(vec3),
                    radius: g.radius,
                    displacement: g.displacement.map(vec3),
                })
                .collect(),
            ..Default::default()
        }
    }
}

/// A request through the server's conversion and the engine: refused with a reason, or answered
/// with one finite displacement per selected node and one force per grasp where the model gives them.
pub fn request(data: &[u8]) -> bool {
    let Ok(fuzzed) = FuzzRequest::arbitrary_take_rest(Unstructured::new(data)) else {
        return false;
    };
    let message = fuzzed.message();
    let Ok(request) = nak::wire::convert::request(&message) else {
        return false;
    };
    let Ok(prediction) = engine().predict(&request) else {
        return false;
    };
    assert_eq!(prediction.displacements.len() % 3, 0);
    assert!(
        prediction.displacements.iter().all(|u| u.is_finite()),
        "an answer holds a non-finite displacement: {message:?}"
    );
    if let Some(forces) = &prediction.grasp_forces {
        assert_eq!(forces.len(), message.grasps.len(), "one force per grasp");
    }
    true
}

/// An MCAP recording, as `nak replay` reads it (complete, cut short, or not a recording at all).
///
/// mcap's reader panics on some malformed files (an index past a record's end, an overflowing
/// count); `read_bytes` catches that at its boundary and refuses the file. libFuzzer's panic hook
/// would abort before the unwinding reaches it, so this target installs a silent hook: a panic that
/// `read_bytes` lets escape still aborts, where the unwinding meets libFuzzer's C frames.
pub fn replay(data: &[u8]) -> bool {
    static SILENT_PANICS: std::sync::Once = std::sync::Once::new();
    SILENT_PANICS.call_once(|| std::panic::set_hook(Box::new(|_| {})));
    nak::record::replay::read_bytes(data, "fuzz.mcap").is_ok()
}
