//! CPU vs GPU Kelvinlet field (K = 20) over synthetic clouds of 10k, 100k and 1M nodes, one request or
//! a batch of 1–32 requests. The CPU evaluates a batch request after request (all cores each); the GPU
//! serves it with as few dispatches as its staging sets allow. GPU times include the upload of the
//! points and the copy of every field into the caller's buffers. After the timings, a table of the
//! GPU's phases (queue, upload, dispatch, wait, copy; medians of 30 calls) says where each row's time
//! goes. The GPU is whatever adapter wgpu finds (name printed first): without a GPU, Mesa's
//! lavapipe, which measures the software path only. `NAK_BENCH_LARGEST=100000` skips the 1M cloud.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use nak::mesh::PriorParams;
use nak::prior::{Coefficients, GpuPhases, InteractionPoints, Kelvinlet, NodeCloud, Workspace, backend};

/// A deterministic cloud filling a 20 cm cube (golden-ratio sequence, no RNG needed).
fn cloud(n: usize) -> NodeCloud {
    let f = |i: usize, a: f64| ((i as f64 * a).fract() - 0.5) * 0.2;
    NodeCloud::new((0..n).map(|i| [f(i, 0.618_034), f(i, 0.754_878), f(i, 0.569_840)]))
}

fn coefficients(kelvinlet: &Kelvinlet, seed: usize) -> Coefficients {
    let mut points = InteractionPoints::default();
    for j in 0..20 {
        let t = (j + seed) as f64;
        points.push(
            j as u32,
            [0.005 * t, 0.03 * t.sin(), 0.02],
            [0.01 * t.cos(), 0.02, -0.01],
        );
    }
    let mut ws = Workspace::default();
    kelvinlet.solve(&points, &mut ws).expect("SPD");
    ws.coefficients
}

fn backends(c: &mut Criterion) {
    let kelvinlet = Kelvinlet::new(PriorParams {
        poisson_ratio: 0.45,
        epsilon: 0.05,
        lambda: 1e-3,
    });
    let largest: usize = std::env::var("NAK_BENCH_LARGEST")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1_000_000);
    let sizes: Vec<usize> = [10_000, 100_000, 1_000_000]
        .into_iter()
        .filter(|&n| n <= largest)
        .collect();
    let clouds: Vec<NodeCloud> = sizes.iter().map(|&n| cloud(n)).collect();
    let gpu = match backend::upload(&clouds.iter().collect::<Vec<_>>()) {
        Ok(gpu) => gpu,
        Err(e) => {
            eprintln!("skipping the GPU benchmarks: {e}");
            return;
        }
    };
    eprintln!("GPU adapter: {}", gpu.adapter());
    let batch: Vec<Coefficients> = (0..32).map(|s| coefficients(&kelvinlet, s)).collect();
    let mut group = c.benchmark_group("prior-backend");
    group.sample_size(10);
    let mut phases = Vec::new();
    for (index, cloud) in clouds.iter().enumerate() {
        let mut out = vec![0.0f32; 3 * cloud.len()];
        let mut fields = vec![vec![0.0f32; 3 * cloud.len()]; 32];
        for requests in [1usize, 8, 32] {
            group.throughput(Throughput::Elements((cloud.len() * requests) as u64));
            let id = format!("{}-nodes/batch-{requests}", cloud.len());
            group.bench_function(BenchmarkId::new("cpu", &id), |b| {
                b.iter(|| {
                    for c in &batch[..requests] {
                        kelvinlet.evaluate_on_cpu(c, cloud, &mut out);
                    }
                })
            });
            let jobs: Vec<(usize, &Coefficients)> = batch[..requests].iter().map(|c| (index, c)).collect();
            let fields = &mut fields[..requests];
            group.bench_function(BenchmarkId::new("gpu", &id), |b| {
                b.iter(|| gpu.evaluate_batch(&kelvinlet, &jobs, fields).expect("GPU"))
            });
            let calls: Vec<GpuPhases> = (0..30)
                .map(|_| gpu.evaluate_batch(&kelvinlet, &jobs, fields).expect("GPU"))
                .collect();
            phases.push((id, median_phases(&calls)));
        }
    }
    group.finish();
    eprintln!("\nGPU phases, medians of 30 calls (µs; upload, dispatch and wait summed over a call's dispatches):");
    eprintln!("| nodes × requests | queue | upload | dispatch | wait | copy | requests per dispatch |");
    eprintln!("|---|---|---|---|---|---|---|");
    for (id, p) in phases {
        eprintln!(
            "| {id} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {} |",
            p.queue_us, p.upload_us, p.dispatch_us, p.wait_us, p.copy_us, p.batch
        );
    }
}

/// Each phase's median over `calls` (phase by phase, not one call's).
fn median_phases(calls: &[GpuPhases]) -> GpuPhases {
    let median = |f: fn(&GpuPhases) -> f32| {
        let mut v: Vec<f32> = calls.iter().map(f).collect();
        v.sort_by(f32::total_cmp);
        v[v.len() / 2]
    };
    GpuPhases {
        queue_us: median(|p| p.queue_us),
        upload_us: median(|p| p.upload_us),
        dispatch_us: median(|p| p.dispatch_us),
        wait_us: median(|p| p.wait_us),
        copy_us: median(|p| p.copy_us),
        batch: calls.iter().map(|p| p.batch).max().unwrap_or(0),
    }
}

criterion_group!(benches, backends);
criterion_main!(benches);
