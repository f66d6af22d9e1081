//! The WGSL Kelvinlet kernel against the CPU kernel, on whatever adapter wgpu finds. CI installs Mesa's
//! lavapipe (`mesa-vulkan-drivers`), a software Vulkan device, so these run without a GPU; a machine
//! with no adapter at all fails them with the install hint rather than skipping.

use std::path::Path;
use std::process::Command;
use std::sync::Arc;

use nak::mesh::PriorParams;
use nak::prior::gpu::{GpuPrior, Resident};
use nak::prior::{InteractionPoints, Kelvinlet, NodeCloud, Workspace};
use rand::{RngExt, SeedableRng};

fn kelvinlet() -> Kelvinlet {
    Kelvinlet::new(PriorParams {
        poisson_ratio: 0.45,
        epsilon: 0.05,
        lambda: 1e-3,
    })
}

/// `n` positions in a 20 cm box, reproducible from `seed`.
fn positions(n: usize, seed: u64) -> Vec<[f64; 3]> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| std::array::from_fn(|_| rng.random_range(-0.1..0.1)))
        .collect()
}

/// K interaction points on distinct nodes of `at`, moved like tissue in a grasp: a translation of
/// a few centimetres plus a smooth stretch, random per `seed`. (Independent random displacements of
/// points closer than ε make the solve cancel huge coefficients, which tests f32 round-off, not
/// the kernel.)
fn points(at: &[[f64; 3]], k: usize, seed: u64) -> InteractionPoints {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let shift: [f64; 3] = std::array::from_fn(|_| rng.random_range(-0.05..0.05));
    let stretch: f64 = rng.random_range(-0.2..0.2);
    let mut p = InteractionPoints::default();
    for j in 0..k {
        let node = j * at.len() / k;
        let x = at[node];
        p.push(node as u32, x, std::array::from_fn(|c| shift[c] + stretch * x[c]));
    }
    p
}

fn gpu(clouds: &[&NodeCloud]) -> Arc<GpuPrior> {
    GpuPrior::new(clouds).unwrap_or_else(|e| panic!("{e}"))
}

/// Largest difference relative to the largest displacement: the CPU and GPU kernels sum the same f32
/// terms in the same order, differing only in sqrt/division rounding, so 1e-5 leaves a wide margin
/// while any formula or indexing slip shows up at 1e-2 or worse.
fn relative_difference(a: &[f32], b: &[f32]) -> f32 {
    let scale = a.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    a.iter().zip(b).fold(0.0f32, |m, (x, y)| m.max((x - y).abs())) / scale
}

#[test]
fn the_gpu_field_equals_the_cpu_field_for_any_k_and_mesh_size() {
    let prior = kelvinlet();
    // 1,000 and 4,099 are not multiples of the 64-invocation workgroup; 64 is exactly one.
    let sizes = [64usize, 1_000, 4_099];
    let nodes: Vec<Vec<[f64; 3]>> = sizes.iter().map(|&n| positions(n, n as u64)).collect();
    let clouds: Vec<NodeCloud> = nodes.iter().map(|p| NodeCloud::new(p.iter().copied())).collect();
    let gpu = gpu(&clouds.iter().collect::<Vec<_>>());
    for (index, (at, cloud)) in nodes.iter().zip(&clouds).enumerate() {
        for k in [1usize, 20, 256] {
            let k = k.min(at.len());
            let mut ws = Workspace::default();
            prior.solve(&points(at, k, 7), &mut ws).unwrap();
            let mut cpu = vec![0.0f32; 3 * at.len()];
            prior.evaluate_on_cpu(&ws.coefficients, cloud, &mut cpu);
            let mut on_gpu = vec![f32::NAN; 3 * at.len()];
            gpu.evaluate(&prior, index, &ws.coefficients, &mut on_gpu).unwrap();
            let difference = relative_difference(&cpu, &on_gpu);
            assert!(difference < 1e-5, "N = {}, K = {k}: {difference:e}", at.len());
        }
    }
}

#[test]
fn a_batch_answers_each_request_as_if_it_were_alone_and_resident_clouds_use_the_gpu() {
    let prior = kelvinlet();
    let (a, b) = (positions(777, 1), positions(130, 2));
    let clouds = [NodeCloud::new(a.iter().copied()), NodeCloud::new(b.iter().copied())];
    let gpu = gpu(&[&clouds[0], &clouds[1]]);
    let mut workspaces: Vec<Workspace> = Vec::new();
    let mut requests = Vec::new();
    for (i, k) in [3usize, 20, 1, 40, 7].into_iter().enumerate() {
        let (cloud, at) = if i % 2 == 0 { (0, &a) } else { (1, &b) };
        let mut ws = Workspace::default();
        prior.solve(&points(at, k, i as u64), &mut ws).unwrap();
        workspaces.push(ws);
        requests.push(cloud);
    }
    let batch: Vec<(usize, &nak::prior::Coefficients)> = requests
        .iter()
        .zip(&workspaces)
        .map(|(&c, ws)| (c, &ws.coefficients))
        .collect();
    let fields = gpu.evaluate_batch(&prior, &batch).unwrap();
    assert_eq!(fields.len(), 5);
    for ((cloud, coefficients), field) in batch.iter().zip(&fields) {
        let mut cpu = vec![0.0f32; 3 * clouds[*cloud].len()];
        prior.evaluate_on_cpu(coefficients, &clouds[*cloud], &mut cpu);
        assert!(relative_difference(&cpu, field) < 1e-5);
    }
    // Concurrent callers share dispatches; each still gets its own answer.
    let mut resident = clouds[0].clone();
    resident.make_resident(Resident {
        gpu: gpu.clone(),
        cloud: 0,
    });
    std::thread::scope(|s| {
        for ws in &workspaces {
            let (prior, resident, cpu_cloud, n) = (&prior, &resident, &clouds[0], a.len());
            s.spawn(move || {
                for _ in 0..20 {
                    let mut on_gpu = vec![0.0f32; 3 * n];
                    prior.evaluate(&ws.coefficients, resident, &mut on_gpu);
                    let mut cpu = vec![0.0f32; 3 * n];
                    prior.evaluate_on_cpu(&ws.coefficients, cpu_cloud, &mut cpu);
                    assert!(relative_difference(&cpu, &on_gpu) < 1e-5);
                }
            });
        }
    });
}

fn nak() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_nak"));
    c.env("RUST_BACKTRACE", "0");
    c
}

#[test]
fn nak_predict_on_the_gpu_matches_the_cpu_and_missing_adapters_are_explained() {
    let dir = tempfile::tempdir().unwrap();
    let grasps = dir.path().join("grasps.json");
    std::fs::write(
        &grasps,
        r#"{"grasps": [{"nodes": [10, 11, 12], "displacement": [0.01, 0.0, -0.02]}]}"#,
    )
    .unwrap();
    let coarse = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/phantom-liver/liver-coarse.msh");
    let run = |backend: &str, out: &str, env: Option<(&str, &str)>| {
        let mut c = nak();
        c.arg("predict").arg("--mesh").arg(&coarse).arg("--grasps").arg(&grasps);
        c.arg("--out")
            .arg(dir.path().join(out))
            .args(["--prior-backend", backend]);
        if let Some((k, v)) = env {
            c.env(k, v);
        }
        c.output().unwrap()
    };
    let read = |name: &str| -> Vec<f32> {
        let bytes = std::fs::read(dir.path().join(name)).unwrap();
        // .npy: a header padded to a multiple of 64 bytes, then little-endian f32.
        let header = 10 + u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        bytemuck::pod_collect_to_vec(&bytes[header..])
    };
    for (backend, out) in [("cpu", "cpu.npy"), ("gpu", "gpu.npy")] {
        let output = run(backend, out, None);
        assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    }
    assert!(relative_difference(&read("cpu.npy"), &read("gpu.npy")) < 1e-5);
    // WGPU_BACKEND names a backend this build does not have: no adapter. `gpu` refuses, `auto` falls back.
    let none = Some(("WGPU_BACKEND", "metal"));
    let refused = run("gpu", "none.npy", none);
    assert!(!refused.status.success());
    let message = String::from_utf8_lossy(&refused.stderr);
    assert!(
        message.contains("no GPU adapter") && message.contains("mesa-vulkan-drivers"),
        "{message}"
    );
    let fallback = run("auto", "auto.npy", none);
    assert!(fallback.status.success());
    assert!(String::from_utf8_lossy(&fallback.stderr).contains("prior on the CPU: no GPU adapter"));
}
