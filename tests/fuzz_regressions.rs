//! Every input the fuzzers ever broke nak with (`fuzz/regressions/<target>/`, kept after the fix) and
//! the seeds the fuzzers start from, through the same targets on stable Rust: a fixed crash stays
//! fixed without a nightly toolchain. With NAK_FUZZ_SEEDS=DIR the seeds are also written to
//! DIR/<target>/ (how `scripts/fuzz` builds its starting corpus).

#[path = "../fuzz/targets.rs"]
mod targets;

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::SystemTime;

use nak::mesh::{self, MeshSource};
use nak::proto::v1 as pb;
use nak::record::{Exchange, RecordConfig, Recorder};

fn repository() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn every_kept_fuzz_input_is_answered_without_a_panic() {
    let root = repository().join("fuzz/regressions");
    let mut replayed = 0;
    for (name, target) in targets::TARGETS {
        let Ok(entries) = std::fs::read_dir(root.join(name)) else {
            continue;
        };
        for entry in entries {
            let path = entry.unwrap().path();
            let input = std::fs::read(&path).unwrap();
            let outcome = std::panic::catch_unwind(|| target(&input));
            assert!(outcome.is_ok(), "{name}: {} panics again", path.display());
            replayed += 1;
        }
    }
    eprintln!("{replayed} kept inputs replayed");
}

/// A seed: the target it feeds, a file name, and its bytes.
type Seed = (&'static str, String, Vec<u8>);

fn file_seed(target: &'static str, path: &Path) -> Seed {
    let name = path
        .strip_prefix(repository())
        .unwrap()
        .to_string_lossy()
        .replace('/', "_");
    (target, name, std::fs::read(path).unwrap())
}

/// Every model manifest in the repository: the shipped networks and the test models.
fn manifests() -> Vec<PathBuf> {
    let mut found = Vec::new();
    for root in ["models/phantom-liver", "tests/models/phantom-liver-coarse"] {
        for entry in std::fs::read_dir(repository().join(root)).unwrap() {
            let manifest = entry.unwrap().path().join("manifest.toml");
            if manifest.exists() {
                found.push(manifest);
            }
        }
    }
    found.sort();
    found
}

/// A recording of three exchanges on the box fixture (one refused), made by nak's recorder.
fn recording() -> Vec<u8> {
    let dir = tempfile::tempdir().unwrap();
    let box_mesh = repository().join("tests/fixtures/box.msh");
    let mesh = Arc::new(mesh::load(&MeshSource::File(box_mesh)).unwrap());
    let recorder = Recorder::start(RecordConfig::new(dir.path().into()), mesh, BTreeMap::new()).unwrap();
    let request = pb::PredictRequest {
        model: "kelvinlet".into(),
        grasps: vec![nak::wire::grasp_message(&nak::engine::Grasp {
            nodes: vec![1, 2, 3],
            displacement: [0.01, 0.0, -0.01],
            ..Default::default()
        })],
        ..Default::default()
    };
    let answer = pb::PredictResponse {
        node_count: 2,
        node_ids: vec![1, 2],
        displacements: nak::wire::f32_bytes(vec![0.01, 0.0, -0.01, 0.005, 0.0, 0.0]),
        ..Default::default()
    };
    for response in [
        Ok(answer.clone()),
        Err((3, "node 99999 is not in the mesh".into())),
        Ok(answer),
    ] {
        let now = SystemTime::now();
        recorder.record(Exchange {
            received: now,
            answered: now,
            request: request.clone(),
            response,
        });
    }
    recorder.close().unwrap();
    let file = std::fs::read_dir(dir.path()).unwrap().next().unwrap().unwrap().path();
    std::fs::read(file).unwrap()
}

fn seeds() -> Vec<Seed> {
    let fixtures = repository().join("tests/fixtures");
    let mut seeds = vec![
        // One cube in six tets: small, so that most of the fuzzer's time goes to mutating structure.
        (
            "msh",
            "cube.msh".into(),
            common::msh_fixture::Fixture::grid(1).to_msh().into_bytes(),
        ),
        file_seed("msh", &fixtures.join("box.msh")),
        file_seed("msh", &fixtures.join("box-binary.msh")),
        file_seed("mesh_config", &fixtures.join("model.toml")),
        file_seed("mesh_config", &repository().join("models/phantom-liver/model.toml")),
    ];
    seeds.extend(manifests().iter().map(|m| file_seed("manifest", m)));
    let recording = recording();
    // A hard kill leaves a file without its summary and footer: replay reads what is complete.
    let cut = recording[..recording.len() * 2 / 3].to_vec();
    seeds.push(("replay", "recording.mcap".into(), recording));
    seeds.push(("replay", "recording-cut.mcap".into(), cut));
    seeds
}

#[test]
fn the_seeds_the_fuzzers_start_from_are_accepted() {
    let seeds = seeds();
    assert!(
        seeds.iter().filter(|s| s.0 == "manifest").count() >= 10,
        "the manifests were not found"
    );
    for (target, name, bytes) in &seeds {
        let (_, run) = targets::TARGETS.iter().find(|t| t.0 == *target).unwrap();
        assert!(run(bytes), "{target}: seed {name} is refused");
    }
    assert!(
        !targets::msh(b"$MeshFormat\n4.1 0 8\n$EndMeshFormat\n"),
        "a mesh without elements"
    );
    if let Some(dir) = std::env::var_os("NAK_FUZZ_SEEDS") {
        for (target, name, bytes) in seeds {
            let folder = Path::new(&dir).join(target);
            std::fs::create_dir_all(&folder).unwrap();
            std::fs::write(folder.join(name), bytes).unwrap();
        }
    }
}
