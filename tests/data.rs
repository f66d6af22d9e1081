//! `nak datagen` and `nak eval` end to end on the coarse phantom: determinism, resumption, chunks
//! readable back, and DCM of the exact model.

use std::path::Path;
use std::process::Command;

use nak::data::dataset;

fn nak() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_nak"));
    c.env("RUST_BACKTRACE", "0");
    c
}

fn coarse() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver/liver-coarse.msh")
}

fn datagen(out: &Path, cache: &Path, seed: &str) -> String {
    let output = nak()
        .arg("datagen")
        .arg("--mesh")
        .arg(coarse())
        .args(["--preset", "tiny", "--chunk-size", "8", "--seed", seed, "--out"])
        .arg(out)
        .arg("--cache-dir")
        .arg(cache)
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    String::from_utf8_lossy(&output.stdout).into_owned()
}

#[test]
fn datagen_is_deterministic_resumable_and_readable() {
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("cache");
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let first = datagen(&a, &cache, "5");
    assert!(
        first.contains("20 samples (12 single, 8 multi) in 3 chunks (0 resumed)"),
        "{first}"
    );
    // Interrupt b after its first chunk: remove the other chunks' completion markers and rerun.
    datagen(&b, &cache, "5");
    for chunk in 1..3 {
        std::fs::remove_file(dataset::chunk_paths(&b, chunk).1).unwrap();
    }
    let resumed = datagen(&b, &cache, "5");
    assert!(resumed.contains("(1 resumed)"), "{resumed}");
    let info = dataset::read_info(&a).unwrap();
    for chunk in 0..info.chunks() {
        let (sa, sb) = (dataset::chunk_paths(&a, chunk), dataset::chunk_paths(&b, chunk));
        assert_eq!(
            std::fs::read(&sa.0).unwrap(),
            std::fs::read(&sb.0).unwrap(),
            "chunk {chunk} fields"
        );
        assert_eq!(
            std::fs::read(&sa.1).unwrap(),
            std::fs::read(&sb.1).unwrap(),
            "chunk {chunk} metadata"
        );
    }
    let samples: Vec<_> = (0..info.chunks())
        .flat_map(|c| dataset::read_chunk(&a, c, info.node_count).unwrap())
        .collect();
    assert_eq!(samples.len(), 20);
    assert_eq!(samples.iter().filter(|(s, _)| s.subset == "multi").count(), 8);
    for (s, field) in &samples {
        assert_eq!(field.len(), 3 * info.node_count);
        // Grasped nodes move exactly as prescribed (f32 storage).
        for g in &s.grasps {
            for &n in &g.nodes {
                for k in 0..3 {
                    assert!((field[3 * n as usize + k] as f64 - g.displacement[k]).abs() < 1e-6);
                }
            }
        }
        assert_eq!(s.split, dataset::split_of(s.index));
    }
    // Another seed draws other grasps; the same arguments on a different dataset are refused.
    let other = dir.path().join("c");
    datagen(&other, &cache, "6");
    assert_ne!(
        std::fs::read(dataset::chunk_paths(&other, 0).1).unwrap(),
        std::fs::read(dataset::chunk_paths(&a, 0).1).unwrap()
    );
    let clash = nak()
        .arg("datagen")
        .arg("--mesh")
        .arg(coarse())
        .args(["--preset", "tiny", "--seed", "7", "--out"])
        .arg(&a)
        .arg("--cache-dir")
        .arg(&cache)
        .output()
        .unwrap();
    assert!(!clash.status.success());
    assert!(String::from_utf8_lossy(&clash.stderr).contains("holds another dataset"));
}

#[test]
fn eval_scores_the_exact_model_at_100_and_writes_json() {
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("cache");
    let data = dir.path().join("data");
    datagen(&data, &cache, "1");
    let json = dir.path().join("eval.json");
    for model in ["green-linear", "kelvinlet"] {
        let output = nak()
            .arg("eval")
            .arg("--data")
            .arg(&data)
            .arg("--mesh")
            .arg(coarse())
            .args(["--split", "all", "--model", model, "--output"])
            .arg(&json)
            .arg("--cache-dir")
            .arg(&cache)
            .output()
            .unwrap();
        assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
        let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
        let combined = &report["subsets"]["combined"];
        assert_eq!(combined["samples"], 20);
        let dcm = combined["dcm"].as_f64().unwrap();
        if model == "green-linear" {
            assert!(dcm > 99.999, "{dcm}");
        } else {
            assert!(dcm < 99.0, "the prior is not the FEM answer: {dcm}");
        }
        assert!(report["subsets"]["single"]["samples"] == 12 && report["subsets"]["multi"]["samples"] == 8);
    }
    // A dataset on another mesh is refused with the reason.
    let wrong = nak().arg("eval").arg("--data").arg(&data).output().unwrap();
    assert!(!wrong.status.success());
    assert!(String::from_utf8_lossy(&wrong.stderr).contains("pass that mesh with --mesh"));
}
