//! Where the Kelvinlet field is evaluated: the one place that chooses between the CPU kernel
//! ([`super::kernel`]) and the GPU ([`super::gpu`]), per node cloud.

use std::sync::Arc;
use std::time::Instant;

use super::cloud::Resident;
use super::gpu::{GpuError, GpuPhases, GpuPrior};
use super::kernel::splits_over_pool;
use super::{Coefficients, InteractionPoints, Kelvinlet, NodeCloud, SolveError, Workspace};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize, serde::Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum PriorBackend {
    /// The vectorized multi-core CPU kernel.
    #[default]
    Cpu,
    /// The WGSL kernel on the first GPU adapter wgpu finds; an error if there is none.
    Gpu,
    /// Measure both on each of the served node sets at start-up and keep the faster for each; CPU if
    /// there is no GPU.
    Auto,
}

/// The most interaction points whose solve (about 40 µs at 32 points) ends while a thread woken at
/// its start is still looking for work.
const PREWAKE_MAX_POINTS: usize = 32;

impl Kelvinlet {
    /// Writes the field of `coefficients` at every node of `cloud` into `out`, row-major (N, 3), on
    /// the GPU when the cloud is resident there (then returning where the time went), else on the
    /// CPU. `out` holds `3 * cloud.len()` values.
    pub fn evaluate(&self, coefficients: &Coefficients, cloud: &NodeCloud, out: &mut [f32]) -> Option<GpuPhases> {
        debug_assert_eq!(
            out.len(),
            3 * cloud.len(),
            "output buffer does not match the node cloud"
        );
        if let Some(r) = cloud.resident() {
            match r.gpu.evaluate(self, r.cloud, coefficients, out) {
                Ok(phases) => return Some(phases),
                // The answer is still owed: the CPU gives the same field, a little later.
                Err(e) => tracing::warn!("GPU prior failed, this request is evaluated on the CPU: {e}"),
            }
        }
        self.evaluate_on_cpu(coefficients, cloud, out);
        None
    }

    /// Solves for `points` and writes their field at every node of `cloud` into `out`: a request's
    /// whole prior. Returns the GPU's phases when the field was evaluated there.
    ///
    /// When the field is about to be split across rayon's pool from one of its threads, another
    /// thread is woken before the solve rather than after it: a sleeping thread takes about as long
    /// to start as the solve itself (20–30 µs on a small virtual machine: `cargo bench --bench
    /// prior`, `solve+field` against `solve` and `field` apart), and rayon keeps a woken thread
    /// looking for work for longer than that before it sleeps again. A longer solve would outlast that
    /// search, and the thread would have to be woken twice.
    pub fn solve_and_evaluate(
        &self,
        points: &InteractionPoints,
        workspace: &mut Workspace,
        cloud: &NodeCloud,
        out: &mut [f32],
    ) -> Result<Option<GpuPhases>, SolveError> {
        let on_cpu = cloud.resident().is_none();
        if points.len() <= PREWAKE_MAX_POINTS && on_cpu && splits_over_pool(cloud, points.len()) {
            rayon::spawn(|| {});
        }
        self.solve(points, workspace)?;
        Ok(self.evaluate(&workspace.coefficients, cloud, out))
    }
}

/// Opens the GPU and uploads `clouds` to it, cloud `i` as its resident cloud `i`.
pub fn upload(clouds: &[&NodeCloud]) -> Result<Arc<GpuPrior>, GpuError> {
    let positions: Vec<Vec<[f32; 3]>> = clouds.iter().map(|c| c.positions().collect()).collect();
    GpuPrior::new(&positions)
}

/// Interaction points for the start-up measurement: K = 20 nodes spread over the cloud.
fn probe(cloud: &NodeCloud) -> InteractionPoints {
    let mut points = InteractionPoints::default();
    let k = cloud.len().min(20);
    for j in 0..k {
        let i = j * cloud.len() / k;
        points.push(i as u32, cloud.position(i).map(f64::from), [0.01, -0.02, 0.005]);
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

/// Applies `backend` to `clouds`, each named for the log (`gpu`: uploads them all and makes them
/// resident; `auto`: uploads them, times a K = 20 field over each on both, and makes resident
/// those the GPU evaluates faster). Returns a sentence saying what was chosen and why.
pub fn attach(
    backend: PriorBackend,
    kelvinlet: &Kelvinlet,
    clouds: &mut [(&str, &mut NodeCloud)],
) -> Result<String, GpuError> {
    if backend == PriorBackend::Cpu {
        return Ok("prior on the CPU (--prior-backend cpu)".into());
    }
    let gpu = match (upload(&clouds.iter().map(|(_, c)| &**c).collect::<Vec<_>>()), backend) {
        (Ok(gpu), _) => gpu,
        (Err(e), PriorBackend::Auto) => return Ok(format!("prior on the CPU: {e}")),
        (Err(e), _) => return Err(e),
    };
    let mut verdicts = Vec::with_capacity(clouds.len());
    for (index, (name, cloud)) in clouds.iter_mut().enumerate() {
        let on_gpu = if backend == PriorBackend::Gpu {
            true
        } else {
            let (cpu, gpu_time) = measure(kelvinlet, cloud, index, &gpu)?;
            let faster = gpu_time < cpu;
            verdicts.push(format!(
                "{name} ({} nodes) on the {}: K = 20 CPU {:.3} ms, GPU {:.3} ms",
                cloud.len(),
                if faster { "GPU" } else { "CPU" },
                cpu * 1e3,
                gpu_time * 1e3
            ));
            faster
        };
        if on_gpu {
            cloud.make_resident(Resident {
                gpu: gpu.clone(),
                cloud: index,
            });
        }
    }
    Ok(match backend {
        PriorBackend::Gpu => format!("prior on the GPU {} (--prior-backend gpu)", gpu.adapter()),
        _ => format!(
            "prior by start-up timing on {} (--prior-backend auto): {}",
            gpu.adapter(),
            verdicts.join("; ")
        ),
    })
}

/// Median time of one K = 20 field over `cloud` on the CPU and on the GPU (where it is resident
/// cloud `index`), including the upload of the points and the readback.
fn measure(kelvinlet: &Kelvinlet, cloud: &NodeCloud, index: usize, gpu: &GpuPrior) -> Result<(f64, f64), GpuError> {
    let mut workspace = Workspace::default();
    kelvinlet
        .solve(&probe(cloud), &mut workspace)
        .map_err(|e| GpuError::Run(e.to_string()))?;
    let c = &workspace.coefficients;
    let mut out = vec![0.0f32; 3 * cloud.len()];
    let cpu = median_seconds(21, || kelvinlet.evaluate_on_cpu(c, cloud, &mut out));
    let mut failure = None;
    let on_gpu = median_seconds(21, || {
        if let Err(e) = gpu.evaluate(kelvinlet, index, c, &mut out) {
            failure = Some(e);
        }
    });
    match failure {
        Some(e) => Err(e),
        None => Ok((cpu, on_gpu)),
    }
}
