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
        // Each scored sample once, whose errors average to the DCM.
        let samples = report["samples"].as_array().unwrap();
        let mut indices: Vec<u64> = samples.iter().map(|s| s["index"].as_u64().unwrap()).collect();
        indices.sort_unstable();
        assert_eq!(indices, (0..20).collect::<Vec<_>>());
        let mean_error = samples.iter().map(|s| s["volume"].as_f64().unwrap()).sum::<f64>() / 20.0;
        assert!(
            (100.0 * (1.0 - mean_error) - dcm).abs() < 1e-9,
            "{mean_error} against {dcm}"
        );
        assert_eq!(samples.iter().filter(|s| s["subset"] == "multi").count(), 8);
        let forces = &report["grasp_forces"]["combined"];
        // 12 single-grasper and 8 two-grasper samples.
        assert_eq!(forces["grasps"], 28, "{report}");
        let force_error = forces["mean_relative_error"].as_f64().unwrap();
        if model == "green-linear" {
            assert!(dcm > 99.999, "{dcm}");
            assert!(force_error < 1e-6, "{force_error}");
        } else {
            assert!(dcm < 99.0, "the prior is not the FEM answer: {dcm}");
            assert!(
                force_error > 0.01,
                "the Kelvinlet's forces are an estimate: {force_error}"
            );
        }
        assert!(report["subsets"]["single"]["samples"] == 12 && report["subsets"]["multi"]["samples"] == 8);
    }
    // A dataset on another mesh is refused with the reason.
    let wrong = nak().arg("eval").arg("--data").arg(&data).output().unwrap();
    assert!(!wrong.status.success());
    assert!(String::from_utf8_lossy(&wrong.stderr).contains("pass that mesh with --mesh"));
}

fn fixture_box() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/box.msh")
}

/// `nak datagen` on the box fixture (small enough for debug builds) with extra arguments.
fn datagen_box(out: &Path, cache: &Path, extra: &[&str]) -> std::process::Output {
    nak()
        .arg("datagen")
        .arg("--mesh")
        .arg(fixture_box())
        .args([
            "--single",
            "6",
            "--multi",
            "0",
            "--chunk-size",
            "3",
            "--seed",
            "3",
            "--out",
        ])
        .arg(out)
        .arg("--cache-dir")
        .arg(cache)
        .args(extra)
        .output()
        .unwrap()
}

fn samples(dir: &Path) -> Vec<(dataset::SampleRecord, Vec<f32>)> {
    let info = dataset::read_info(dir).unwrap();
    (0..info.chunks())
        .flat_map(|c| dataset::read_chunk(dir, c, info.node_count).unwrap())
        .collect()
}

#[test]
fn nonlinear_datagen_is_deterministic_resumable_and_shares_grasps_with_linear() {
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("cache");
    let (a, b, linear) = (dir.path().join("a"), dir.path().join("b"), dir.path().join("linear"));
    let nonlinear = ["--regime", "nonlinear"];
    let first = datagen_box(&a, &cache, &nonlinear);
    assert!(first.status.success(), "{}", String::from_utf8_lossy(&first.stderr));
    let report = String::from_utf8_lossy(&first.stdout);
    assert!(report.contains("6 samples, 0 failed"), "{report}");
    // The second run reads the cached preload; interrupting it after one chunk and resuming gives
    // the same bytes.
    assert!(datagen_box(&b, &cache, &nonlinear).status.success());
    std::fs::remove_file(dataset::chunk_paths(&b, 1).1).unwrap();
    let resumed = datagen_box(&b, &cache, &nonlinear);
    assert!(String::from_utf8_lossy(&resumed.stdout).contains("(1 resumed)"));
    let again = datagen_box(&b, &cache, &nonlinear);
    assert!(String::from_utf8_lossy(&again.stdout).contains("every chunk was already complete"));
    for chunk in 0..2 {
        let (sa, sb) = (dataset::chunk_paths(&a, chunk), dataset::chunk_paths(&b, chunk));
        assert_eq!(std::fs::read(&sa.0).unwrap(), std::fs::read(&sb.0).unwrap());
        assert_eq!(std::fs::read(&sa.1).unwrap(), std::fs::read(&sb.1).unwrap());
    }
    let states = path_states_are_the_converged_load_steps(&a, &b);
    assert!(report.contains(&format!("{states} load-path states kept")), "{report}");
    assert!(datagen_box(&linear, &cache, &[]).status.success());
    assert!(
        !dataset::path_states_path(&linear, 0).exists(),
        "a linear solve has no load path"
    );
    let (nonlinear_samples, linear_samples) = (samples(&a), samples(&linear));
    assert_eq!(nonlinear_samples.len(), 6);
    for ((n, n_field), (l, l_field)) in nonlinear_samples.iter().zip(&linear_samples) {
        assert_eq!(
            n.grasps(),
            l.grasps(),
            "sample {} draws the same grasps in both regimes",
            n.index
        );
        // Both store the force of each grasp. The paper's Mooney–Rivlin liver is stiffer than its
        // linear one (small-strain μ0 = 2(C10 + C01) = 7.18 kPa against 0.69 kPa): the nonlinear force
        // is about μ0/μ times the linear one, give or take what large strains and gravity change.
        for (nf, lf) in n.forces().unwrap().iter().zip(l.forces().unwrap()) {
            let size = |f: &[f64; 3]| f.iter().map(|v| v * v).sum::<f64>().sqrt();
            let ratio = size(nf) / size(&lf) / (7.18 / 0.69);
            assert!((0.3..3.0).contains(&ratio), "nonlinear {nf:?}, linear {lf:?}");
        }
        let solver = n.solver.as_ref().unwrap();
        assert!(solver.failure.is_none() && solver.stats.load_steps >= 1 && solver.stats.newton_iterations >= 1);
        // Relative to the preloaded state, grasped nodes move exactly as prescribed.
        for (node, u) in n.prescribed() {
            for k in 0..3 {
                assert!((n_field[3 * node as usize + k] as f64 - u[k]).abs() < 1e-6);
            }
        }
        // Large grasps: the nonlinear field differs from the linear one, but not wildly.
        let difference: f32 = n_field
            .iter()
            .zip(l_field)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        let size: f32 = l_field.iter().map(|x| x.abs()).fold(0.0, f32::max);
        assert!(difference > 1e-4 * size && difference < size, "{difference} vs {size}");
    }
}

/// Each chunk of `a` keeps, beside it, the converged states of its solves' load steps before the
/// last: the same bytes in `b` (made the same way, one chunk resumed), one state per load step but
/// the last of each sample, in order of load, its grasped nodes moved by that share of the grasp.
/// Returns how many states `a` keeps.
fn path_states_are_the_converged_load_steps(a: &Path, b: &Path) -> usize {
    let by_index: std::collections::BTreeMap<u64, (dataset::SampleRecord, Vec<f32>)> =
        samples(a).into_iter().map(|s| (s.0.index, s)).collect();
    let mut states = 0;
    for chunk in 0..2 {
        let bytes = std::fs::read(dataset::path_states_path(a, chunk)).unwrap();
        assert_eq!(bytes, std::fs::read(dataset::path_states_path(b, chunk)).unwrap());
        let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
        let sample: Vec<i64> = bytemuck::pod_collect_to_vec(st.tensor("sample").unwrap().data());
        let load: Vec<f64> = bytemuck::pod_collect_to_vec(st.tensor("load").unwrap().data());
        let field: Vec<f32> = bytemuck::pod_collect_to_vec(st.tensor("displacement").unwrap().data());
        let nodes = field.len() / 3 / sample.len();
        for (record, _) in by_index.values().filter(|(r, _)| r.index / 3 == chunk as u64) {
            let mine: Vec<usize> = (0..sample.len())
                .filter(|&p| sample[p] as u64 == record.index)
                .collect();
            let steps = record.solver.as_ref().unwrap().stats.load_steps;
            assert_eq!(mine.len(), steps - 1, "sample {}", record.index);
            let loads: Vec<f64> = mine.iter().map(|&p| load[p]).collect();
            assert!(loads.windows(2).all(|w| w[0] < w[1]) && loads.iter().all(|t| 0.0 < *t && *t < 1.0));
            for &p in &mine {
                for (node, u) in record.prescribed() {
                    for k in 0..3 {
                        let got = field[(p * nodes + node as usize) * 3 + k] as f64;
                        assert!(
                            (got - load[p] * u[k]).abs() < 1e-6,
                            "state {p} node {node}: {got} vs {}",
                            load[p] * u[k]
                        );
                    }
                }
            }
            states += mine.len();
        }
    }
    assert!(
        states >= 6,
        "{states} states: every sample took more than one load step"
    );
    states
}

#[test]
fn failed_nonlinear_samples_are_recorded_and_left_out_of_eval() {
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("cache");
    let data = dir.path().join("data");
    // A normal run caches the gravity preload, which the crippled options below could not solve.
    assert!(
        datagen_box(&dir.path().join("warm"), &cache, &["--regime", "nonlinear"])
            .status
            .success()
    );
    // One Newton iteration and no step cuts: grasps of several centimetres cannot converge.
    let output = datagen_box(
        &data,
        &cache,
        &[
            "--regime",
            "nonlinear",
            "--max-newton-iterations",
            "1",
            "--max-step-cuts",
            "0",
        ],
    );
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let all = samples(&data);
    let failed: Vec<_> = all.iter().filter(|(s, _)| s.failed()).collect();
    let summary = String::from_utf8_lossy(&output.stdout);
    assert!(!failed.is_empty(), "{summary}");
    // The summary counts the failures by why they failed, and the counts add up.
    let because = summary
        .lines()
        .find_map(|line| line.strip_prefix("failed because: "))
        .unwrap_or_else(|| panic!("no failure reasons in {summary}"));
    let counted: usize = because
        .split("; ")
        .map(|part| {
            part.split(' ')
                .next()
                .and_then(|n| n.parse::<usize>().ok())
                .unwrap_or(0)
        })
        .sum();
    assert_eq!(counted, failed.len(), "{because}");
    for (s, field) in &failed {
        let reason = s.solver.as_ref().unwrap().failure.as_ref().unwrap();
        assert!(
            reason.contains("load step") && reason.contains("residual history"),
            "{reason}"
        );
        assert!(
            field.iter().all(|v| v.is_nan()),
            "a failed sample has no field to mistake for truth"
        );
    }
    let json = dir.path().join("eval.json");
    let eval = nak()
        .arg("eval")
        .arg("--data")
        .arg(&data)
        .arg("--mesh")
        .arg(fixture_box())
        .args(["--split", "all", "--output"])
        .arg(&json)
        .output()
        .unwrap();
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap_or_default()).unwrap_or(serde_json::Value::Null);
    if failed.len() == all.len() {
        assert!(!eval.status.success(), "nothing left to score");
    } else {
        assert!(eval.status.success(), "{}", String::from_utf8_lossy(&eval.stderr));
        assert_eq!(report["failed_samples"].as_array().unwrap().len(), failed.len());
        assert_eq!(
            report["subsets"]["combined"]["samples"].as_u64().unwrap() as usize,
            all.len() - failed.len()
        );
        assert!(String::from_utf8_lossy(&eval.stdout).contains("left out"));
    }
}

/// Every file of a dataset directory, by name.
fn files(dir: &Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                std::fs::read(&p).unwrap(),
            )
        })
        .collect()
}

fn join(out: &Path, shards: &[&Path]) -> std::process::Output {
    nak()
        .args(["dataset", "join", "--out"])
        .arg(out)
        .args(shards)
        .output()
        .unwrap()
}

fn refused(output: &std::process::Output, words: &[&str]) {
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "accepted; stderr {stderr}");
    for w in words {
        assert!(stderr.contains(w), "{w:?} missing from {stderr}");
    }
}

#[test]
fn a_set_made_in_shards_or_chunk_ranges_is_the_set_one_run_makes() {
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("cache");
    let path = |name: &str| dir.path().join(name);
    let nonlinear = ["--regime", "nonlinear"];
    assert!(datagen_box(&path("whole"), &cache, &nonlinear).status.success());
    for shard in ["0/2", "1/2"] {
        let out = path(&format!("shard-{}", &shard[..1]));
        let run = datagen_box(&out, &cache, &[&nonlinear[..], &["--shard", shard]].concat());
        assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
        assert!(String::from_utf8_lossy(&run.stdout).contains(&format!("3 samples (shard {shard}")));
        // A shard holds its own chunks only: chunk c belongs to shard c mod 2.
        let index: usize = shard[..1].parse().unwrap();
        assert!(dataset::chunk_paths(&out, index).1.is_file());
        assert!(!dataset::chunk_paths(&out, 1 - index).1.exists());
    }
    let (first, second) = (path("shard-0"), path("shard-1"));
    let joined = join(&path("joined"), &[&second, &first]);
    assert!(joined.status.success(), "{}", String::from_utf8_lossy(&joined.stderr));
    let (mut joined, mut whole) = (files(&path("joined")), files(&path("whole")));
    let (joined_mesh, whole_mesh) = (joined.remove("mesh.safetensors"), whole.remove("mesh.safetensors"));
    assert!(dataset::same_mesh_file(&joined_mesh.unwrap(), &whole_mesh.unwrap()));
    assert_eq!(joined, whole);

    // Resuming a shard under another shard number, or out of range.
    refused(
        &datagen_box(&first, &cache, &[&nonlinear[..], &["--shard", "1/2"]].concat()),
        &["holds another dataset", "shard"],
    );
    for bad in ["2/2", "0/0", "1-2"] {
        refused(&datagen_box(&path("bad"), &cache, &["--shard", bad]), &[bad]);
    }
    // Joining: a shard missing, given twice, of another dataset, incomplete, or a whole dataset.
    refused(&join(&path("j1"), &[&first]), &["all 2 shards are needed"]);
    refused(&join(&path("j2"), &[&first, &first]), &["given twice"]);
    let other = path("other-settings");
    let settings = ["--shard", "1/2", "--max-step-cuts", "5"];
    assert!(
        datagen_box(&other, &cache, &[&nonlinear[..], &settings].concat())
            .status
            .success()
    );
    refused(
        &join(&path("j3"), &[&first, &other]),
        &["another dataset", "\"max_step_cuts\":5", "\"max_step_cuts\":12"],
    );
    let linear = path("linear-shard");
    assert!(datagen_box(&linear, &cache, &["--shard", "1/2"]).status.success());
    refused(&join(&path("j4"), &[&first, &linear]), &["another dataset", "regime"]);
    std::fs::remove_file(dataset::chunk_paths(&second, 1).1).unwrap();
    refused(
        &join(&path("j5"), &[&first, &second]),
        &["incomplete", "[1]", "--shard 1/2"],
    );
    refused(&join(&path("j6"), &[&path("whole"), &first]), &["not a shard"]);
    refused(&join(&path("whole"), &[&first, &second]), &["not empty"]);

    // Chunk ranges: chunk 1 here, chunk 0 on "another machine" copied in, and a run without a range
    // finds nothing left to make; the set is the whole run's.
    let (here, elsewhere) = (path("here"), path("elsewhere"));
    for (out, range) in [(&here, "1"), (&elsewhere, "0-0")] {
        let run = datagen_box(out, &cache, &[&nonlinear[..], &["--chunks", range]].concat());
        assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
        let stdout = String::from_utf8_lossy(&run.stdout);
        assert!(stdout.contains("3 samples (chunks"), "{stdout}");
    }
    assert!(dataset::chunk_paths(&here, 1).1.is_file() && !dataset::chunk_paths(&here, 0).1.exists());
    for (name, bytes) in files(&elsewhere) {
        if name.starts_with("chunk-00000") {
            std::fs::write(here.join(name), bytes).unwrap();
        }
    }
    let rest = datagen_box(&here, &cache, &nonlinear);
    assert!(String::from_utf8_lossy(&rest.stdout).contains("(2 resumed)"));
    let (mut here, mut whole) = (files(&here), files(&path("whole")));
    let (here_mesh, whole_mesh) = (here.remove("mesh.safetensors"), whole.remove("mesh.safetensors"));
    assert!(dataset::same_mesh_file(&here_mesh.unwrap(), &whole_mesh.unwrap()));
    assert_eq!(here, whole);
    for (bad, message) in [
        ("2", "the set has 2 chunks, numbered 0 to 1"),
        ("1-0", "the last chunk comes before the first"),
        ("one", "is not a chunk range"),
    ] {
        refused(&datagen_box(&path("bad-range"), &cache, &["--chunks", bad]), &[message]);
    }
}

#[test]
fn data_of_two_volumetric_laws_is_never_mixed() {
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("cache");
    let path = |name: &str| dir.path().join(name);
    // The box again, its model.toml naming the law before (ln J)².
    let old_law = path("old-law");
    std::fs::create_dir(&old_law).unwrap();
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures");
    std::fs::copy(fixtures.join("box.msh"), old_law.join("box.msh")).unwrap();
    let config = std::fs::read_to_string(fixtures.join("model.toml")).unwrap();
    let config = config + "\n[hyperelastic]\nvolumetric_law = \"j-minus-one-squared\"\n";
    std::fs::write(old_law.join("model.toml"), config).unwrap();
    let datagen_old = |out: &Path, extra: &[&str]| {
        nak()
            .args(["datagen", "--mesh"])
            .arg(old_law.join("box.msh"))
            .args(["--single", "6", "--multi", "0", "--chunk-size", "3", "--seed", "3"])
            .args(["--regime", "nonlinear", "--out"])
            .arg(out)
            .arg("--cache-dir")
            .arg(&cache)
            .args(extra)
            .output()
            .unwrap()
    };
    let new = ["--regime", "nonlinear", "--shard", "0/2"];
    let made = datagen_box(&path("new"), &cache, &new);
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
    let made = datagen_old(&path("old"), &["--shard", "1/2"]);
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
    for (name, law) in [("new", "ln-j-squared"), ("old", "j-minus-one-squared")] {
        let info = std::fs::read_to_string(path(name).join("dataset.json")).unwrap();
        assert!(info.contains(&format!("\"volumetric_law\": \"{law}\"")), "{info}");
        // The solver's settings are recorded beside the law.
        assert!(info.contains("\"intermediate_tolerance\": 0.001"), "{info}");
        assert!(info.contains("\"rings\": 2"), "{info}");
        assert!(info.contains("\"max_load_step\": 1.0"), "{info}");
    }
    // A load step that is no fraction of the grasp is refused before anything is solved.
    let no_step = [&new[..], &["--max-load-step", "0"]].concat();
    refused(
        &datagen_box(&path("no-step"), &cache, &no_step),
        &["--max-load-step 0", "(0, 1]"],
    );
    // Resumed with the graspers' neighbourhood solved another way, a set is refused, naming how.
    let other_solver = [&new[..], &["--elimination-rings", "0"]].concat();
    refused(
        &datagen_box(&path("new"), &cache, &other_solver),
        &["holds another dataset", "solver", "\"rings\":2", "\"elimination\":null"],
    );
    // Each law has its own gravity preload in the cache: neither is read for the other.
    let preloads = std::fs::read_dir(&cache)
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .file_name()
                .to_string_lossy()
                .starts_with("preload-")
        })
        .count();
    assert_eq!(preloads, 2);
    // Joining the two halves, or resuming one under the other law, is refused with both laws named.
    let both = ["volumetric_law", "\"ln-j-squared\"", "\"j-minus-one-squared\""];
    refused(&join(&path("joined"), &[&path("new"), &path("old")]), &both);
    refused(
        &datagen_old(&path("new"), &["--shard", "0/2"]),
        &["holds another dataset", both[1], both[2]],
    );
    // Scoring data of one law on a mesh configured with the other is refused too.
    let eval = nak()
        .args([
            "eval",
            "--model",
            "green-tangent",
            "--green-tangent",
            "--split",
            "all",
            "--mesh",
        ])
        .arg(fixture_box())
        .arg("--data")
        .arg(path("old"))
        .arg("--cache-dir")
        .arg(&cache)
        .output()
        .unwrap();
    refused(
        &eval,
        &[
            "j-minus-one-squared (κ/2)(J − 1)²",
            "ln-j-squared (κ/2)(ln J)²",
            "model.toml",
        ],
    );
}
