//! The WGSL Kelvinlet kernel against the CPU kernel, on whatever adapter wgpu finds. CI installs Mesa's
//! lavapipe (`mesa-vulkan-drivers`), a software Vulkan device, so these run without a GPU; a machine
//! with no adapter at all fails them with the install hint rather than skipping.

use std::path::Path;
use std::process::Command;
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

use nak::mesh::PriorParams;
use nak::prior::gpu::{GpuPrior, STAGING_SETS};
use nak::prior::{Coefficients, InteractionPoints, Kelvinlet, NodeCloud, Resident, Workspace, backend};
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

/// One device at a time in this process. With four tests each opening the NVIDIA H100 at once, 3
/// of 8 runs hung or crashed (driver 580.159.04), with and without the leader overlapping
/// dispatches; one test at a time, 10 of 10 runs passed. A server opens one device.
static ONE_DEVICE: Mutex<()> = Mutex::new(());

fn gpu(clouds: &[&NodeCloud]) -> (MutexGuard<'static, ()>, Arc<GpuPrior>) {
    let alone = ONE_DEVICE.lock().unwrap_or_else(PoisonError::into_inner);
    (alone, backend::upload(clouds).unwrap_or_else(|e| panic!("{e}")))
}

/// The solved coefficients of `points(at, k, seed)`.
fn coefficients(prior: &Kelvinlet, at: &[[f64; 3]], k: usize, seed: u64) -> Coefficients {
    let mut ws = Workspace::default();
    prior.solve(&points(at, k, seed), &mut ws).unwrap();
    ws.coefficients
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
    let (_alone, gpu) = gpu(&clouds.iter().collect::<Vec<_>>());
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
    let (_alone, gpu) = gpu(&[&clouds[0], &clouds[1]]);
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
    let mut fields: Vec<Vec<f32>> = batch
        .iter()
        .map(|(c, _)| vec![f32::NAN; 3 * clouds[*c].len()])
        .collect();
    let phases = gpu.evaluate_batch(&prior, &batch, &mut fields).unwrap();
    assert_eq!(phases.batch, 5, "{phases:?}");
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

#[test]
fn many_calls_reuse_the_staging_ring_and_each_sees_its_own_field() {
    let prior = kelvinlet();
    let (a, b) = (positions(500, 3), positions(2_000, 4));
    let clouds = [NodeCloud::new(a.iter().copied()), NodeCloud::new(b.iter().copied())];
    let (_alone, gpu) = gpu(&[&clouds[0], &clouds[1]]);
    // Far more calls than staging sets, alternating clouds and K (the upload buffer grows past its
    // first size at K = 400), each field checked: a set reused before its last reader was done,
    // or an upload left from an earlier call, would show as a wrong field.
    for call in 0..40u64 {
        let (index, at) = if call % 2 == 0 { (0, &a) } else { (1, &b) };
        let k = [1usize, 20, 400, 7][call as usize % 4];
        let c = coefficients(&prior, at, k, call);
        let mut cpu = vec![0.0f32; 3 * at.len()];
        prior.evaluate_on_cpu(&c, &clouds[index], &mut cpu);
        let mut on_gpu = vec![f32::NAN; 3 * at.len()];
        let phases = gpu.evaluate(&prior, index, &c, &mut on_gpu).unwrap();
        assert_eq!(phases.batch, 1, "a lone caller is its own dispatch: {phases:?}");
        assert!(phases.wait_us > 0.0, "{phases:?}");
        let difference = relative_difference(&cpu, &on_gpu);
        assert!(difference < 1e-5, "call {call}, K = {k}: {difference:e}");
    }
}

#[test]
fn a_batch_larger_than_the_staging_ring_is_split_never_refused() {
    let prior = kelvinlet();
    let at = positions(300, 5);
    let cloud = NodeCloud::new(at.iter().copied());
    let (_alone, gpu) = gpu(&[&cloud]);
    let requests = gpu.capacity(0) * STAGING_SETS + 5;
    let solved: Vec<Coefficients> = (0..requests)
        .map(|i| coefficients(&prior, &at, 1 + i % 30, i as u64))
        .collect();
    let batch: Vec<(usize, &Coefficients)> = solved.iter().map(|c| (0, c)).collect();
    let mut fields = vec![vec![f32::NAN; 3 * at.len()]; requests];
    let phases = gpu.evaluate_batch(&prior, &batch, &mut fields).unwrap();
    assert_eq!(phases.batch as usize, gpu.capacity(0), "{phases:?}");
    for (i, (c, field)) in solved.iter().zip(&fields).enumerate() {
        let mut cpu = vec![0.0f32; 3 * at.len()];
        prior.evaluate_on_cpu(c, &cloud, &mut cpu);
        assert!(relative_difference(&cpu, field) < 1e-5, "request {i} of {requests}");
    }
}

#[test]
fn concurrent_callers_with_batches_of_their_own_all_get_their_answers() {
    let prior = kelvinlet();
    let (a, b) = (positions(900, 6), positions(64, 7));
    let clouds = [NodeCloud::new(a.iter().copied()), NodeCloud::new(b.iter().copied())];
    let (_alone, gpu) = gpu(&[&clouds[0], &clouds[1]]);
    // Eight threads, each with batches of 1 to 45 requests over both clouds, share the device: whoever
    // leads submits the others' requests too, and every answer must reach its own caller.
    std::thread::scope(|s| {
        for thread in 0..8u64 {
            let (prior, gpu, clouds, a, b) = (&prior, &gpu, &clouds, &a, &b);
            s.spawn(move || {
                for round in 0..6u64 {
                    let size = 1 + ((thread * 7 + round * 13) % 45) as usize;
                    let requests: Vec<(usize, Coefficients)> = (0..size)
                        .map(|i| {
                            let index = (i + thread as usize) % 2;
                            let at = if index == 0 { a } else { b };
                            (
                                index,
                                coefficients(prior, at, 1 + i % 12, thread * 1000 + round * 50 + i as u64),
                            )
                        })
                        .collect();
                    let batch: Vec<(usize, &Coefficients)> = requests.iter().map(|(i, c)| (*i, c)).collect();
                    let mut fields: Vec<Vec<f32>> = batch
                        .iter()
                        .map(|(i, _)| vec![f32::NAN; 3 * clouds[*i].len()])
                        .collect();
                    gpu.evaluate_batch(prior, &batch, &mut fields).unwrap();
                    for ((index, c), field) in batch.iter().zip(&fields) {
                        let mut cpu = vec![0.0f32; 3 * clouds[*index].len()];
                        prior.evaluate_on_cpu(c, &clouds[*index], &mut cpu);
                        assert!(
                            relative_difference(&cpu, field) < 1e-5,
                            "thread {thread}, round {round}"
                        );
                    }
                }
            });
        }
    });
}

#[test]
fn requests_that_do_not_fit_the_resident_clouds_are_refused_before_the_device_sees_them() {
    let prior = kelvinlet();
    let at = positions(100, 8);
    let cloud = NodeCloud::new(at.iter().copied());
    let (_alone, gpu) = gpu(&[&cloud]);
    let c = coefficients(&prior, &at, 5, 1);
    let wrong_size = gpu.evaluate(&prior, 0, &c, &mut vec![0.0; 3 * 99]).unwrap_err();
    assert!(
        wrong_size
            .to_string()
            .contains("output of 297 values for cloud 0 of 100 nodes"),
        "{wrong_size}"
    );
    let no_cloud = gpu.evaluate(&prior, 3, &c, &mut vec![0.0; 300]).unwrap_err();
    assert!(no_cloud.to_string().contains("no resident cloud 3"), "{no_cloud}");
    // The device still serves after the refusals.
    let mut field = vec![f32::NAN; 300];
    gpu.evaluate(&prior, 0, &c, &mut field).unwrap();
    let mut cpu = vec![0.0f32; 300];
    prior.evaluate_on_cpu(&c, &cloud, &mut cpu);
    assert!(relative_difference(&cpu, &field) < 1e-5);
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
