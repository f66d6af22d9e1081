//! Where the Kelvinlet field is evaluated: CPU, GPU, or whichever measures faster at start-up.

use std::time::Instant;

use super::gpu::{GpuError, GpuPrior, Resident};
use super::{InteractionPoints, Kelvinlet, NodeCloud, Workspace};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize, serde::Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum PriorBackend {
    /// The vectorized multi-core CPU kernel.
    #[default]
    Cpu,
    /// The WGSL kernel on the first GPU adapter wgpu finds; an error if there is none.
    Gpu,
    /// Measure both on the served mesh at start-up and keep the faster; CPU if there is no GPU.
    Auto,
}

/// Interaction points for the start-up measurement: K = 20 nodes spread over the cloud.
fn probe(cloud: &NodeCloud) -> InteractionPoints {
    let mut points = InteractionPoints::default();
    let k = cloud.len().min(20);
    for j in 0..k {
        let i = j * cloud.len() / k;
        let p = cloud.position(i / super::kernel::BLOCK, i % super::kernel::BLOCK);
        points.push(i as u32, p.map(f64::from), [0.01, -0.02, 0.005]);
    }
    points
}

/// Median seconds of `runs` calls of `f`, after two warm-up calls.
fn median_seconds(runs: usize, mut f: impl FnMut()) -> f64 {
    f();
    f();
    let mut times: Vec<f64> = (0..runs)
        .map(|_| {
            let start = Instant::now();
            f();
            start.elapsed().as_secs_f64()
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[times.len() / 2]
}

/// Applies `backend` to `clouds` (the first is the one measured for `auto`): for GPU, uploads them
/// and makes them resident. Returns a sentence saying what was chosen and why.
pub fn attach(backend: PriorBackend, kelvinlet: &Kelvinlet, clouds: &mut [&mut NodeCloud]) -> Result<String, GpuError> {
    if backend == PriorBackend::Cpu {
        return Ok("prior on the CPU (--prior-backend cpu)".into());
    }
    let gpu = match (GpuPrior::new(&clouds.iter().map(|c| &**c).collect::<Vec<_>>()), backend) {
        (Ok(gpu), _) => gpu,
        (Err(e), PriorBackend::Auto) => return Ok(format!("prior on the CPU: {e}")),
        (Err(e), _) => return Err(e),
    };
    let choice = if backend == PriorBackend::Gpu {
        format!("prior on the GPU {} (--prior-backend gpu)", gpu.adapter())
    } else {
        let (cpu, gpu_time) = measure(kelvinlet, clouds[0], &gpu)?;
        let verdict = format!(
            "K = 20 over {} nodes: CPU {:.3} ms, GPU {} {:.3} ms",
            clouds[0].len(),
            cpu * 1e3,
            gpu.adapter(),
            gpu_time * 1e3
        );
        if cpu <= gpu_time {
            return Ok(format!("prior on the CPU, faster at start-up ({verdict})"));
        }
        format!("prior on the GPU, faster at start-up ({verdict})")
    };
    for (index, cloud) in clouds.iter_mut().enumerate() {
        cloud.make_resident(Resident {
            gpu: gpu.clone(),
            cloud: index,
        });
    }
    Ok(choice)
}

/// Median time of one K = 20 field over `cloud` on the CPU and on the GPU, where it was uploaded
/// first (including upload of the points and readback).
fn measure(kelvinlet: &Kelvinlet, cloud: &NodeCloud, gpu: &GpuPrior) -> Result<(f64, f64), GpuError> {
    let mut workspace = Workspace::default();
    kelvinlet
        .solve(&probe(cloud), &mut workspace)
        .map_err(|e| GpuError::Run(e.to_string()))?;
    let c = &workspace.coefficients;
    let mut out = vec![0.0f32; 3 * cloud.len()];
    let cpu = median_seconds(21, || kelvinlet.evaluate_on_cpu(c, cloud, &mut out));
    let mut failure = None;
    let on_gpu = median_seconds(21, || {
        if let Err(e) = gpu.evaluate(kelvinlet, 0, c, &mut out) {
            failure = Some(e);
        }
    });
    match failure {
        Some(e) => Err(e),
        None => Ok((cpu, on_gpu)),
    }
}
