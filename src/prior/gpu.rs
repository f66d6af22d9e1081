//! The Kelvinlet field on the GPU (wgpu, WGSL kernel `field.wgsl`).
//!
//! Node clouds are uploaded once into one persistent buffer. A request sends only its K points and
//! coefficients (32 bytes each) and reads its (N, 3) field back. The (3K)×(3K) solve stays on the
//! CPU in f64: for K ≤ 256 it takes microseconds, less than one GPU round trip, and f32 on the GPU
//! would cost accuracy.
//!
//! There is no GPU thread. A caller that finds the device idle *leads*: it submits its own request,
//! together with every request that queued meanwhile (one dispatch, workgroup row = request, as
//! many as fit [`GpuPrior::capacity`]), and polls until the field is in mapped host memory,
//! submitting what arrives meanwhile into the free staging sets. Callers that arrive while it
//! leads wait for their answers, or to lead the next dispatch. Each caller then
//! copies its own field straight from the mapped memory into its answer, so a dispatch's copies run
//! on as many threads as it served requests, and a lone request is never handed to another thread.
//! A ring of [`STAGING_SETS`] staging sets (an upload buffer that stays mapped for writing between
//! dispatches, and a readback buffer) lets a dispatch be submitted while earlier ones are still
//! being read, so that a batch larger than one dispatch streams through the ring.

use std::collections::{HashMap, VecDeque};
use std::ops::Range;
use std::panic::AssertUnwindSafe;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, OnceLock};
use std::time::{Duration, Instant};

use rayon::prelude::*;
use wgpu::util::DeviceExt;

use super::{Coefficients, Kelvinlet};

/// Requests served by one dispatch at most.
pub const MAX_BATCH: usize = 32;
/// Dispatches that can be in flight or being read at once.
pub const STAGING_SETS: usize = 3;
/// Readback memory per staging set (or one field of the largest cloud, if more): a dispatch takes
/// as many requests as fit, so a batch of large fields is split into dispatches that overlap in the
/// ring.
const STAGING_BYTES: usize = 16 << 20;
const WORKGROUP: u32 = 64;
/// Each request's rows start at a multiple of this many floats (256 bytes) in the field and readback
/// buffers: a mapped range must start at a multiple of 8 bytes.
const ROW_ALIGN: usize = 64;
/// Bytes of job table reserved ahead of the points in an upload buffer (a multiple of 256).
const JOB_TABLE_BYTES: usize = (MAX_BATCH * std::mem::size_of::<JobEntry>()).next_multiple_of(256);
/// How long a leader polls a hardware GPU before it blocks in the driver: a small dispatch is done
/// in tens of microseconds, less than a blocked thread takes to be woken.
const SPIN: Duration = Duration::from_millis(1);
/// A dispatch not done after this long is given up (a hung device): the CPU answers instead.
const TIMEOUT: Duration = Duration::from_secs(10);
/// Fields larger than this are copied out of mapped memory by rayon's pool, in chunks.
const PARALLEL_COPY_BYTES: usize = 1 << 19;
const COPY_CHUNK_BYTES: usize = 1 << 18;

#[derive(Debug, Clone, thiserror::Error)]
pub enum GpuError {
    #[error(
        "no GPU adapter found (wgpu tried Vulkan; for a software one install Mesa's lavapipe: apt-get install mesa-vulkan-drivers)"
    )]
    NoAdapter,
    #[error("the GPU adapter {adapter} refused a device: {message}")]
    Device { adapter: String, message: String },
    #[error("GPU evaluation failed: {0}")]
    Run(String),
    #[error("the GPU did not finish a dispatch within {0:?}")]
    Timeout(Duration),
    #[error("the GPU prior has stopped (a thread failed while holding it)")]
    Stopped,
}

/// Where the time of a GPU evaluation went, in microseconds. For a call that several dispatches
/// served ([`GpuPrior::evaluate_batch`] beyond one dispatch), upload, dispatch, wait and copy are
/// summed over them; dispatches overlap each other's copies, so the sum can exceed the call's wall
/// time.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct GpuPhases {
    /// From the call until a dispatch took the request: another dispatch was being submitted, or
    /// every staging set was in use.
    pub queue_us: f32,
    /// Writing the dispatch's job table and interaction points into its mapped upload buffer.
    pub upload_us: f32,
    /// Encoding and submitting the dispatch (upload copies, kernel, copy to the readback buffer).
    pub dispatch_us: f32,
    /// From submission until the field was in mapped host memory: the kernel, the copy across the
    /// bus, and the leader noticing (polling) or being woken.
    pub wait_us: f32,
    /// Copying the field out of mapped memory into the answer.
    pub copy_us: f32,
    /// Requests in the dispatch (the largest, if several served the call).
    pub batch: u32,
}

impl GpuPhases {
    /// Adds the account of another dispatch that served the same call.
    fn add_dispatch(&mut self, other: &GpuPhases) {
        self.queue_us = self.queue_us.max(other.queue_us);
        self.upload_us += other.upload_us;
        self.dispatch_us += other.dispatch_us;
        self.wait_us += other.wait_us;
        self.batch = self.batch.max(other.batch);
    }
}

/// One request's part of a dispatch.
struct Job {
    cloud: usize,
    constants: [f32; 3],
    /// Per point: position (xyz, 0) and coefficient (xyz, 0).
    points: Vec<[f32; 8]>,
    /// A resident basis and its coefficients g: Φ g is added to the field in the same dispatch.
    basis: Option<(usize, Vec<f32>)>,
}

/// A reduced basis Φ resident on the GPU (uploaded by [`GpuPrior::upload_basis`]).
#[derive(Debug, Clone)]
pub struct GpuBasis {
    gpu: Arc<GpuPrior>,
    id: usize,
    modes: usize,
}

impl GpuBasis {
    /// Whether fields over clouds resident on `gpu` can add this basis in their dispatch.
    pub fn lives_on(&self, gpu: &Arc<GpuPrior>) -> bool {
        Arc::ptr_eq(&self.gpu, gpu)
    }

    pub fn modes(&self) -> usize {
        self.modes
    }

    pub fn gpu(&self) -> &Arc<GpuPrior> {
        &self.gpu
    }
}

/// The device, its resident clouds and bases, and the requests it is serving; cheap to share.
pub struct GpuPrior {
    adapter: String,
    device: wgpu::Device,
    queue: wgpu::Queue,
    /// (offset, length) of each cloud in the positions buffer, in nodes.
    clouds: Vec<(usize, usize)>,
    /// Floats of field one dispatch holds (its requests' rows, each aligned).
    field_floats: usize,
    spin: Duration,
    /// Bases uploaded so far; ids below it are valid.
    bases: AtomicUsize,
    /// Device buffers and the pipeline: held while a dispatch is encoded or a basis uploaded.
    resources: Mutex<Resources>,
    state: Mutex<State>,
    /// Signalled whenever answers are published, a staging set is freed, or leadership is given up.
    changed: Condvar,
}

impl std::fmt::Debug for GpuPrior {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuPrior").field("adapter", &self.adapter).finish()
    }
}

/// Job table entry, laid out as `Job` in field.wgsl.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct JobEntry {
    cloud_offset: u32,
    cloud_len: u32,
    point_offset: u32,
    point_count: u32,
    out_offset: u32,
    a: f32,
    b: f32,
    epsilon_sq: f32,
    /// 0 without a basis.
    modes: u32,
    /// Where the cloud's rows of the basis start in `basis`, in floats.
    basis_offset: u32,
    /// Where g starts in `points`, in vec4s.
    coefficient_offset: u32,
}

struct Resources {
    pipeline: wgpu::ComputePipeline,
    positions: wgpu::Buffer,
    points: wgpu::Buffer,
    jobs: wgpu::Buffer,
    field: wgpu::Buffer,
    /// Every uploaded basis, one after another; `basis_starts[id][cloud]` is where a cloud's rows
    /// start.
    basis: wgpu::Buffer,
    basis_host: Vec<f32>,
    basis_starts: Vec<Vec<usize>>,
    bind_group: wgpu::BindGroup,
    /// The dispatch being encoded, on the host (kept to reuse their memory).
    entries: Vec<JobEntry>,
    point_rows: Vec<[f32; 8]>,
}

/// Who waits for what; every field changes under the one lock.
struct State {
    pending: VecDeque<Queued>,
    in_flight: VecDeque<InFlight>,
    answers: HashMap<u64, Result<Ready, GpuError>>,
    sets: Vec<StagingSet>,
    leading: bool,
    next_ticket: u64,
    next_dispatch: u64,
}

struct Queued {
    ticket: u64,
    job: Job,
    since: Instant,
}

struct StagingSet {
    /// MAP_WRITE: mapped whenever the set is free (at creation, then again when each dispatch
    /// that used it is done), so a dispatch's inputs are written straight into it.
    upload: wgpu::Buffer,
    /// MAP_READ: the dispatch's fields, mapped while its requesters copy them out.
    readback: wgpu::Buffer,
    /// Requesters still to copy their field out of `readback`; the last one unmaps it.
    readers: usize,
    free: bool,
}

/// A submitted dispatch.
struct InFlight {
    id: u64,
    set: usize,
    submission: wgpu::SubmissionIndex,
    mapping: Arc<Mapping>,
    /// Each request's ticket, its bytes in the readback buffer, and how long it queued.
    tickets: Vec<(u64, Range<u64>, f32)>,
    upload_us: f32,
    dispatch_us: f32,
    submitted: Instant,
}

/// The two mappings a dispatch ends with: its readback buffer for reading, its upload buffer for
/// writing the next dispatch on the same set.
struct Mapping {
    outstanding: AtomicUsize,
    failed: AtomicBool,
}

impl Mapping {
    fn callback(self: &Arc<Self>) -> impl FnOnce(Result<(), wgpu::BufferAsyncError>) + Send + 'static {
        let mapping = self.clone();
        move |result| {
            if result.is_err() {
                mapping.failed.store(true, Ordering::Release);
            }
            mapping.outstanding.fetch_sub(1, Ordering::AcqRel);
        }
    }

    fn done(&self) -> bool {
        self.outstanding.load(Ordering::Acquire) == 0
    }
}

/// A field ready to be copied out.
struct Ready {
    /// The dispatch that computed it, numbered in order of submission.
    dispatch: u64,
    set: usize,
    readback: wgpu::Buffer,
    bytes: Range<u64>,
    phases: GpuPhases,
}

/// The process's one wgpu instance, never dropped. Dropping the last handle to it unloads the Vulkan
/// driver (`dlclose`), but Mesa's software drivers (llvmpipe/lavapipe, and the LLVM inside them)
/// register `atexit` destructors: a process whose GPU worker released the device just before `exit`
/// then crashed in those handlers (seen in CI as a segfault after a successful `nak predict`).
fn process_instance() -> &'static wgpu::Instance {
    static INSTANCE: OnceLock<wgpu::Instance> = OnceLock::new();
    INSTANCE.get_or_init(|| wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env()))
}

fn failure(e: impl std::fmt::Display) -> GpuError {
    GpuError::Run(e.to_string())
}

/// Runs `f`, turning a panic (wgpu reports a validation error or a lost device by panicking) into
/// an error, so the request is answered by the CPU and the other requests go on.
fn catching<T>(f: impl FnOnce() -> Result<T, GpuError>) -> Result<T, GpuError> {
    std::panic::catch_unwind(AssertUnwindSafe(f)).unwrap_or_else(|panic| {
        let message = panic
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| panic.downcast_ref::<&str>().copied())
            .unwrap_or("a panic in wgpu");
        Err(GpuError::Run(message.to_owned()))
    })
}

/// Floats a request's field takes in the field and readback buffers: its (N, 3) rows, aligned.
fn rows(nodes: usize) -> usize {
    (3 * nodes).next_multiple_of(ROW_ALIGN)
}

fn micros(since: Instant) -> f32 {
    since.elapsed().as_secs_f32() * 1e6
}

impl GpuPrior {
    /// Opens the first GPU adapter wgpu finds and uploads `clouds` (each cloud's node positions);
    /// their indices identify them later.
    pub fn new(clouds: &[Vec<[f32; 3]>]) -> Result<Arc<Self>, GpuError> {
        let adapter = pollster::block_on(process_instance().request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            ..Default::default()
        }))
        .map_err(|_| GpuError::NoAdapter)?;
        let info = adapter.get_info();
        let name = format!("{} ({:?}, {:?})", info.name, info.device_type, info.backend);
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("nak prior"),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device {
            adapter: name.clone(),
            message: e.to_string(),
        })?;
        let largest = clouds.iter().map(Vec::len).max().unwrap_or(0).max(1);
        let widest = u64::from(WORKGROUP) * u64::from(limits.max_compute_workgroups_per_dimension);
        if largest as u64 > widest {
            return Err(GpuError::Device {
                adapter: name,
                message: format!("a cloud of {largest} nodes is more than one dispatch row covers ({widest})"),
            });
        }
        let binding = limits.max_storage_buffer_binding_size.min(limits.max_buffer_size) as usize;
        let field_floats = (STAGING_BYTES / 4).max(rows(largest)).min(binding / 4);
        if rows(largest) > field_floats {
            return Err(GpuError::Device {
                adapter: name,
                message: format!("a cloud of {largest} nodes has more rows than the adapter binds ({binding} bytes)"),
            });
        }
        let spin = if info.device_type == wgpu::DeviceType::Cpu {
            // A software device computes on the CPU cores a spinning caller would take from it.
            Duration::ZERO
        } else {
            SPIN
        };
        let resources = catching(|| Ok(Resources::new(&device, clouds, 4 * field_floats)))?;
        let sets = (0..STAGING_SETS)
            .map(|_| {
                StagingSet::new(
                    &device,
                    4 * field_floats as u64,
                    (JOB_TABLE_BYTES + 32 * 256 * MAX_BATCH) as u64,
                )
            })
            .collect();
        let mut offset = 0;
        let ranges = clouds
            .iter()
            .map(|c| {
                offset += c.len();
                (offset - c.len(), c.len())
            })
            .collect();
        tracing::info!(adapter = %name, clouds = clouds.len(), "GPU prior ready");
        Ok(Arc::new(Self {
            adapter: name,
            device,
            queue,
            clouds: ranges,
            field_floats,
            spin,
            bases: AtomicUsize::new(0),
            resources: Mutex::new(resources),
            state: Mutex::new(State {
                pending: VecDeque::new(),
                in_flight: VecDeque::new(),
                answers: HashMap::new(),
                sets,
                leading: false,
                next_ticket: 0,
                next_dispatch: 0,
            }),
            changed: Condvar::new(),
        }))
    }

    pub fn adapter(&self) -> &str {
        &self.adapter
    }

    /// Requests over resident cloud `cloud` that one dispatch serves; a larger batch is split into
    /// several.
    pub fn capacity(&self, cloud: usize) -> usize {
        let len = self.clouds.get(cloud).map_or(0, |c| c.1);
        (self.field_floats / rows(len).max(1)).clamp(1, MAX_BATCH)
    }

    fn job(kelvinlet: &Kelvinlet, cloud: usize, c: &Coefficients, basis: Option<(usize, Vec<f32>)>) -> Job {
        Job {
            cloud,
            constants: [kelvinlet.a as f32, kelvinlet.b as f32, kelvinlet.epsilon_sq as f32],
            points: (0..c.len())
                .map(|j| [c.x[j], c.y[j], c.z[j], 0.0, c.kx[j], c.ky[j], c.kz[j], 0.0])
                .collect(),
            basis,
        }
    }

    /// Evaluates several requests, each (cloud index, coefficients), writing request `i`'s (N, 3)
    /// field into `outs[i]`; the batch is split into as many dispatches as it needs.
    pub fn evaluate_batch<O: AsMut<[f32]> + Send>(
        &self,
        kelvinlet: &Kelvinlet,
        requests: &[(usize, &Coefficients)],
        outs: &mut [O],
    ) -> Result<GpuPhases, GpuError> {
        let jobs = requests
            .iter()
            .map(|&(cloud, c)| Self::job(kelvinlet, cloud, c, None))
            .collect();
        self.run(jobs, outs)
    }

    /// Writes the field of `coefficients` over resident cloud `cloud` into `out` ((N, 3) rows).
    pub fn evaluate(
        &self,
        kelvinlet: &Kelvinlet,
        cloud: usize,
        coefficients: &Coefficients,
        out: &mut [f32],
    ) -> Result<GpuPhases, GpuError> {
        self.run(vec![Self::job(kelvinlet, cloud, coefficients, None)], &mut [out])
    }

    /// Writes `Σ_j Γ_j k_j + Φ g` over resident cloud `cloud` into `out` in one dispatch: the
    /// Kelvinlet field of `coefficients` (none for a direct model) plus the basis's field of `g`.
    pub fn evaluate_with_basis(
        &self,
        kelvinlet: &Kelvinlet,
        cloud: usize,
        coefficients: &Coefficients,
        basis: &GpuBasis,
        g: &[f32],
        out: &mut [f32],
    ) -> Result<GpuPhases, GpuError> {
        if g.len() != basis.modes {
            return Err(GpuError::Run(format!(
                "{} coefficients for a basis of {} modes",
                g.len(),
                basis.modes
            )));
        }
        let job = Self::job(kelvinlet, cloud, coefficients, Some((basis.id, g.to_vec())));
        self.run(vec![job], &mut [out])
    }

    /// Keeps a basis on the device: `per_cloud[c]` is Φ's rows [len_c, 3, M] for resident cloud `c`.
    pub fn upload_basis(self: &Arc<Self>, per_cloud: Vec<Vec<f32>>, modes: usize) -> Result<GpuBasis, GpuError> {
        let fits = per_cloud.len() == self.clouds.len()
            && per_cloud
                .iter()
                .zip(&self.clouds)
                .all(|(rows, &(_, len))| rows.len() == 3 * len * modes);
        if !fits || modes == 0 {
            return Err(GpuError::Run(format!(
                "a basis of {modes} modes whose rows do not match the resident clouds {:?}",
                self.clouds.iter().map(|c| c.1).collect::<Vec<_>>()
            )));
        }
        let mut resources = self.resources.lock().map_err(|_| GpuError::Stopped)?;
        let id = catching(|| resources.upload_basis(&self.device, &per_cloud, modes))?;
        self.bases.fetch_max(id + 1, Ordering::AcqRel);
        Ok(GpuBasis {
            gpu: self.clone(),
            id,
            modes,
        })
    }

    fn lock(&self) -> Result<MutexGuard<'_, State>, GpuError> {
        self.state.lock().map_err(|_| GpuError::Stopped)
    }

    /// Serves `jobs`, job `i`'s field into `outs[i]`: queues them, leads dispatches while no one
    /// else does, and copies each field out as soon as its dispatch is done.
    fn run<O: AsMut<[f32]> + Send>(&self, jobs: Vec<Job>, outs: &mut [O]) -> Result<GpuPhases, GpuError> {
        if jobs.len() != outs.len() {
            return Err(GpuError::Run(format!(
                "{} requests with {} outputs",
                jobs.len(),
                outs.len()
            )));
        }
        for (job, out) in jobs.iter().zip(outs.iter_mut()) {
            self.check(job, out.as_mut().len())?;
        }
        let since = Instant::now();
        let mut state = self.lock()?;
        let mut waiting = HashMap::with_capacity(jobs.len());
        for (index, job) in jobs.into_iter().enumerate() {
            let ticket = state.next_ticket;
            state.next_ticket += 1;
            state.pending.push_back(Queued { ticket, job, since });
            waiting.insert(ticket, index);
        }
        let mut phases = GpuPhases::default();
        let mut dispatches = Vec::new();
        let mut first_error = None;
        while !waiting.is_empty() {
            let ready: Vec<(usize, Result<Ready, GpuError>)> = waiting
                .iter()
                .filter_map(|(ticket, &index)| state.answers.remove(ticket).map(|answer| (index, answer)))
                .collect();
            if ready.is_empty() {
                if !state.leading {
                    let progressed;
                    (state, progressed) = self.lead(state, &waiting)?;
                    if progressed {
                        continue;
                    }
                }
                // Another caller leads, or every staging set is still being read: either will
                // signal when it is done.
                state = self.changed.wait(state).map_err(|_| GpuError::Stopped)?;
                continue;
            }
            waiting.retain(|_, index| ready.iter().all(|(i, _)| i != index));
            drop(state);
            let copying = Instant::now();
            let copied = copy_out(ready, outs);
            phases.copy_us += micros(copying);
            state = self.lock()?;
            for Copied { set, outcome } in copied {
                if let Some(set) = set {
                    release(&mut state.sets[set]);
                }
                match outcome {
                    Ok((dispatch, account)) if !dispatches.contains(&dispatch) => {
                        dispatches.push(dispatch);
                        phases.add_dispatch(&account);
                    }
                    Ok(_) => {}
                    Err(e) => {
                        first_error.get_or_insert(e);
                    }
                }
            }
            self.changed.notify_all();
        }
        first_error.map_or(Ok(phases), Err)
    }

    /// How many of the queued requests, from the front, one dispatch takes: as many as their rows
    /// fit the field buffer, at most [`MAX_BATCH`], at least one.
    fn fitting(&self, pending: &VecDeque<Queued>) -> usize {
        let mut floats = 0;
        let fit = pending
            .iter()
            .take(MAX_BATCH)
            .take_while(|q| {
                floats += rows(self.clouds[q.job.cloud].1);
                floats <= self.field_floats
            })
            .count();
        fit.max(1).min(pending.len())
    }

    /// Refuses a job that does not fit the resident clouds and bases before it is queued.
    fn check(&self, job: &Job, out: usize) -> Result<(), GpuError> {
        let Some(&(_, len)) = self.clouds.get(job.cloud) else {
            return Err(GpuError::Run(format!("no resident cloud {}", job.cloud)));
        };
        if out != 3 * len {
            return Err(GpuError::Run(format!(
                "output of {out} values for cloud {} of {len} nodes",
                job.cloud
            )));
        }
        match &job.basis {
            Some((id, _)) if *id >= self.bases.load(Ordering::Acquire) => {
                Err(GpuError::Run(format!("no resident basis {id}")))
            }
            _ => Ok(()),
        }
    }

    /// Submits the queued requests into free staging sets and publishes each dispatch when it is
    /// done, until one of `mine` is answered or nothing is left to submit or wait for. Says whether
    /// it submitted or published anything.
    fn lead<'a>(
        &'a self,
        mut state: MutexGuard<'a, State>,
        mine: &HashMap<u64, usize>,
    ) -> Result<(MutexGuard<'a, State>, bool), GpuError> {
        state.leading = true;
        let mut progressed = false;
        loop {
            while !state.pending.is_empty() {
                let Some(set) = state.sets.iter().position(|s| s.free) else {
                    break;
                };
                let take = self.fitting(&state.pending);
                let batch: Vec<Queued> = state.pending.drain(..take).collect();
                let staging = &mut state.sets[set];
                staging.free = false;
                let (upload, readback) = (staging.upload.clone(), staging.readback.clone());
                let id = state.next_dispatch;
                state.next_dispatch += 1;
                drop(state);
                let submitted = catching(|| self.dispatch(&batch, id, set, upload, readback));
                state = self.lock()?;
                progressed = true;
                match submitted {
                    Ok((flight, grown)) => {
                        if let Some(upload) = grown {
                            state.sets[set].upload = upload;
                        }
                        state.in_flight.push_back(flight);
                    }
                    Err(e) => {
                        tracing::warn!("a GPU dispatch could not be submitted: {e}");
                        self.renew(&mut state.sets[set]);
                        for queued in batch {
                            state.answers.insert(queued.ticket, Err(e.clone()));
                        }
                        self.changed.notify_all();
                    }
                }
            }
            let Some(oldest) = state.in_flight.front() else {
                break;
            };
            let (mapping, submission, submitted) =
                (oldest.mapping.clone(), oldest.submission.clone(), oldest.submitted);
            drop(state);
            let polled = catching(|| self.poll(&mapping, &submission, submitted));
            state = self.lock()?;
            if matches!(polled, Ok(false)) {
                // Still running: submit what arrived meanwhile, then look again.
                continue;
            }
            let Some(flight) = state.in_flight.pop_front() else {
                break;
            };
            self.publish(&mut state, flight, polled.map(|_| ()));
            progressed = true;
            self.changed.notify_all();
            if mine.keys().any(|ticket| state.answers.contains_key(ticket)) {
                break;
            }
        }
        state.leading = false;
        self.changed.notify_all();
        Ok((state, progressed))
    }

    /// Writes a dispatch's inputs into its set's upload buffer and submits it: the upload copies,
    /// the kernel, the copy of its fields into the set's readback buffer, and the mappings it ends
    /// with. Returns the set's new upload buffer when the old one was too small.
    fn dispatch(
        &self,
        batch: &[Queued],
        id: u64,
        set: usize,
        mut upload: wgpu::Buffer,
        readback: wgpu::Buffer,
    ) -> Result<(InFlight, Option<wgpu::Buffer>), GpuError> {
        let started = Instant::now();
        let mut resources = self.resources.lock().map_err(|_| GpuError::Stopped)?;
        let r = &mut *resources;
        r.entries.clear();
        r.point_rows.clear();
        let mut tickets = Vec::with_capacity(batch.len());
        let mut out = 0;
        for queued in batch {
            let job = &queued.job;
            let (cloud_offset, len) = self.clouds[job.cloud];
            let point_offset = r.point_rows.len();
            r.point_rows.extend_from_slice(&job.points);
            let (modes, basis_offset, coefficient_offset) = match &job.basis {
                None => (0, 0, 0),
                Some((id, g)) => {
                    let start = r.basis_starts[*id][job.cloud];
                    // g rides in the points buffer, 8 floats (two vec4s) per entry.
                    let at = 2 * r.point_rows.len();
                    r.point_rows.extend(
                        g.chunks(8)
                            .map(|c| std::array::from_fn(|i| c.get(i).copied().unwrap_or(0.0))),
                    );
                    (g.len() as u32, start as u32, at as u32)
                }
            };
            r.entries.push(JobEntry {
                cloud_offset: cloud_offset as u32,
                cloud_len: len as u32,
                point_offset: point_offset as u32,
                point_count: job.points.len() as u32,
                out_offset: out as u32,
                a: job.constants[0],
                b: job.constants[1],
                epsilon_sq: job.constants[2],
                modes,
                basis_offset,
                coefficient_offset,
            });
            let bytes = (4 * out) as u64..(4 * (out + 3 * len)) as u64;
            tickets.push((queued.ticket, bytes, (started - queued.since).as_secs_f32() * 1e6));
            out += rows(len);
        }
        let table_bytes = std::mem::size_of_val(r.entries.as_slice());
        let point_bytes = std::mem::size_of_val(r.point_rows.as_slice());
        let needed = (JOB_TABLE_BYTES + point_bytes) as u64;
        let grown = (needed > upload.size()).then(|| {
            upload = StagingSet::upload_buffer(&self.device, needed.next_power_of_two());
            upload.clone()
        });
        {
            let mut view = upload.get_mapped_range_mut(..needed).map_err(failure)?;
            view.slice(..table_bytes)
                .copy_from_slice(bytemuck::cast_slice(&r.entries));
            view.slice(JOB_TABLE_BYTES..)
                .copy_from_slice(bytemuck::cast_slice(&r.point_rows));
        }
        upload.unmap();
        let upload_us = micros(started);

        let submitting = Instant::now();
        if point_bytes as u64 > r.points.size() {
            r.points = storage(
                &self.device,
                "points",
                point_bytes.next_power_of_two(),
                wgpu::BufferUsages::COPY_DST,
            );
            r.rebind(&self.device);
        }
        let fields_end = tickets.iter().map(|t| t.1.end).max().unwrap_or(0).max(4);
        let widest = r.entries.iter().map(|e| e.cloud_len).max().unwrap_or(0);
        let mut encoder = self.device.create_command_encoder(&Default::default());
        encoder.copy_buffer_to_buffer(&upload, 0, &r.jobs, 0, table_bytes as u64);
        if point_bytes > 0 {
            encoder.copy_buffer_to_buffer(&upload, JOB_TABLE_BYTES as u64, &r.points, 0, point_bytes as u64);
        }
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&r.pipeline);
            pass.set_bind_group(0, &r.bind_group, &[]);
            pass.dispatch_workgroups(widest.div_ceil(WORKGROUP), batch.len() as u32, 1);
        }
        encoder.copy_buffer_to_buffer(&r.field, 0, &readback, 0, fields_end);
        let mapping = Arc::new(Mapping {
            outstanding: AtomicUsize::new(2),
            failed: AtomicBool::new(false),
        });
        encoder.map_buffer_on_submit(&readback, wgpu::MapMode::Read, ..fields_end, mapping.callback());
        encoder.map_buffer_on_submit(&upload, wgpu::MapMode::Write, .., mapping.callback());
        let submission = self.queue.submit([encoder.finish()]);
        let dispatch_us = micros(submitting);
        drop(resources);
        let flight = InFlight {
            id,
            set,
            submission,
            mapping,
            tickets,
            upload_us,
            dispatch_us,
            submitted: Instant::now(),
        };
        Ok((flight, grown))
    }

    /// Whether a dispatch's buffers are mapped yet: the device is polled once while the dispatch
    /// has run for less than the spin budget (the leader then submits what arrived meanwhile and
    /// asks again), after that the leader blocks in the driver until it is done.
    fn poll(
        &self,
        mapping: &Mapping,
        submission: &wgpu::SubmissionIndex,
        submitted: Instant,
    ) -> Result<bool, GpuError> {
        if !mapping.done() {
            let waited = submitted.elapsed();
            if waited >= TIMEOUT {
                return Err(GpuError::Timeout(TIMEOUT));
            }
            let poll = if waited < self.spin {
                wgpu::PollType::Poll
            } else {
                wgpu::PollType::Wait {
                    submission_index: Some(submission.clone()),
                    timeout: Some(TIMEOUT - waited),
                }
            };
            match self.device.poll(poll) {
                Ok(_) => {}
                Err(wgpu::PollError::Timeout) => return Err(GpuError::Timeout(TIMEOUT)),
                Err(e) => return Err(failure(e)),
            }
        }
        if !mapping.done() {
            return Ok(false);
        }
        if mapping.failed.load(Ordering::Acquire) {
            return Err(GpuError::Run("the dispatch's buffers could not be mapped".into()));
        }
        Ok(true)
    }

    /// Hands each request of a finished dispatch its answer: where its field lies in the mapped
    /// readback buffer, or why there is none.
    fn publish(&self, state: &mut State, flight: InFlight, waited: Result<(), GpuError>) {
        let wait_us = micros(flight.submitted);
        let batch = flight.tickets.len() as u32;
        if let Err(e) = waited {
            tracing::warn!("a GPU dispatch failed: {e}");
            self.renew(&mut state.sets[flight.set]);
            for (ticket, ..) in flight.tickets {
                state.answers.insert(ticket, Err(e.clone()));
            }
            return;
        }
        let staging = &mut state.sets[flight.set];
        staging.readers = flight.tickets.len();
        let readback = staging.readback.clone();
        for (ticket, bytes, queue_us) in flight.tickets {
            let phases = GpuPhases {
                queue_us,
                upload_us: flight.upload_us,
                dispatch_us: flight.dispatch_us,
                wait_us,
                copy_us: 0.0,
                batch,
            };
            let ready = Ready {
                dispatch: flight.id,
                set: flight.set,
                readback: readback.clone(),
                bytes,
                phases,
            };
            state.answers.insert(ticket, Ok(ready));
        }
    }

    /// Replaces a staging set whose dispatch failed (its buffers may be left mapped, or waiting to
    /// be): fresh buffers of the same sizes. If even that fails, the old set is reused and its next
    /// dispatch fails too, so no request waits for a set that never comes back.
    fn renew(&self, staging: &mut StagingSet) {
        let sizes = (staging.readback.size(), staging.upload.size());
        match catching(|| Ok(StagingSet::new(&self.device, sizes.0, sizes.1))) {
            Ok(fresh) => *staging = fresh,
            Err(e) => {
                tracing::warn!("a GPU staging set could not be replaced: {e}");
                staging.readers = 0;
                staging.free = true;
            }
        }
    }
}

/// A requester is done with its field in `staging`; the last one unmaps it and frees the set.
fn release(staging: &mut StagingSet) {
    staging.readers = staging.readers.saturating_sub(1);
    if staging.readers == 0 {
        staging.readback.unmap();
        staging.free = true;
    }
}

/// One answer copied out of its staging set.
struct Copied {
    /// The staging set it was read from (none for a failed dispatch).
    set: Option<usize>,
    /// The dispatch that computed it and that dispatch's account, or why there is no field.
    outcome: Result<(u64, GpuPhases), GpuError>,
}

/// Copies each answered field into its output (`ready[k].0` indexes `outs`), on rayon's pool when
/// there are several.
fn copy_out<O: AsMut<[f32]> + Send>(ready: Vec<(usize, Result<Ready, GpuError>)>, outs: &mut [O]) -> Vec<Copied> {
    let mut by_index: HashMap<usize, Result<Ready, GpuError>> = ready.into_iter().collect();
    let targets: Vec<(&mut [f32], Result<Ready, GpuError>)> = outs
        .iter_mut()
        .enumerate()
        .filter_map(|(i, out)| by_index.remove(&i).map(|answer| (out.as_mut(), answer)))
        .collect();
    let copy = |(out, answer): (&mut [f32], Result<Ready, GpuError>)| match answer {
        Err(e) => Copied {
            set: None,
            outcome: Err(e),
        },
        Ok(ready) => Copied {
            set: Some(ready.set),
            outcome: copy_field(&ready.readback, ready.bytes, out).map(|()| (ready.dispatch, ready.phases)),
        },
    };
    if targets.len() > 1 {
        targets.into_par_iter().map(copy).collect()
    } else {
        targets.into_iter().map(copy).collect()
    }
}

/// Copies `bytes` of the mapped `readback` buffer into `out`, split over rayon's pool when large.
fn copy_field(readback: &wgpu::Buffer, bytes: Range<u64>, out: &mut [f32]) -> Result<(), GpuError> {
    let out: &mut [u8] = bytemuck::cast_slice_mut(out);
    if bytes.is_empty() {
        return Ok(());
    }
    let view = readback.get_mapped_range(bytes).map_err(failure)?;
    let field: &[u8] = &view;
    if field.len() != out.len() {
        return Err(GpuError::Run(format!(
            "a field of {} bytes for an output of {}",
            field.len(),
            out.len()
        )));
    }
    if out.len() >= PARALLEL_COPY_BYTES {
        out.par_chunks_mut(COPY_CHUNK_BYTES)
            .zip(field.par_chunks(COPY_CHUNK_BYTES))
            .for_each(|(to, from)| to.copy_from_slice(from));
    } else {
        out.copy_from_slice(field);
    }
    Ok(())
}

fn storage(device: &wgpu::Device, label: &str, size: usize, usage: wgpu::BufferUsages) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: size.max(16) as u64,
        usage: wgpu::BufferUsages::STORAGE | usage,
        mapped_at_creation: false,
    })
}

impl StagingSet {
    fn new(device: &wgpu::Device, readback: u64, upload: u64) -> Self {
        Self {
            upload: Self::upload_buffer(device, upload),
            readback: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("readback"),
                size: readback,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            readers: 0,
            free: true,
        }
    }

    /// An upload buffer, mapped for writing from the start.
    fn upload_buffer(device: &wgpu::Device, size: u64) -> wgpu::Buffer {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("upload"),
            size: size.next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT),
            usage: wgpu::BufferUsages::MAP_WRITE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: true,
        })
    }
}

impl Resources {
    fn new(device: &wgpu::Device, clouds: &[Vec<[f32; 3]>], field_bytes: usize) -> Self {
        let mut positions: Vec<[f32; 4]> = clouds.iter().flatten().map(|&[x, y, z]| [x, y, z, 0.0]).collect();
        if positions.is_empty() {
            positions.push([0.0; 4]);
        }
        let positions = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("node positions"),
            contents: bytemuck::cast_slice(&positions),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let source = wgpu::ShaderModuleDescriptor {
            label: Some("field.wgsl"),
            source: wgpu::ShaderSource::Wgsl(include_str!("field.wgsl").into()),
        };
        // SAFETY: every index the kernel computes is in bounds by construction on the host: a job's
        // cloud range lies in `positions` (made from the same clouds), its points and g in `points`
        // (grown to each dispatch's size), its basis rows in `basis` (`upload_basis` checks them
        // against the clouds), its rows in `field` (dispatches take only the jobs whose rows fit), and
        // the dispatch has one row per job-table entry. Runtime bounds checks would only cost time.
        let module = unsafe { device.create_shader_module_trusted(source, wgpu::ShaderRuntimeChecks::unchecked()) };
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("kelvinlet field"),
            layout: None,
            module: &module,
            entry_point: Some("main"),
            compilation_options: Default::default(),
            cache: None,
        });
        let copy_in = wgpu::BufferUsages::COPY_DST;
        let points = storage(device, "points", 32 * 256 * MAX_BATCH, copy_in);
        let jobs = storage(device, "jobs", JOB_TABLE_BYTES, copy_in);
        let field = storage(device, "field", field_bytes, wgpu::BufferUsages::COPY_SRC);
        let basis = storage(device, "basis", 16, copy_in);
        let bind_group = bind(device, &pipeline, [&positions, &points, &jobs, &field, &basis]);
        Self {
            pipeline,
            positions,
            points,
            jobs,
            field,
            basis,
            basis_host: Vec::new(),
            basis_starts: Vec::new(),
            bind_group,
            entries: Vec::with_capacity(MAX_BATCH),
            point_rows: Vec::new(),
        }
    }

    fn rebind(&mut self, device: &wgpu::Device) {
        self.bind_group = bind(
            device,
            &self.pipeline,
            [&self.positions, &self.points, &self.jobs, &self.field, &self.basis],
        );
    }

    /// Appends a basis (each cloud's rows [len, 3, M]) to the device's basis buffer, rebuilt whole
    /// (uploads happen at load, not per request), and returns its id. On the device each cloud's
    /// part is stored mode by mode, [M, 3, len], so that neighbouring invocations (nodes) read
    /// neighbouring words.
    fn upload_basis(&mut self, device: &wgpu::Device, per_cloud: &[Vec<f32>], modes: usize) -> Result<usize, GpuError> {
        let mut host = self.basis_host.clone();
        let mut starts = Vec::with_capacity(per_cloud.len());
        for rows in per_cloud {
            starts.push(host.len());
            let len = rows.len() / (3 * modes);
            let start = host.len();
            host.resize(start + rows.len(), 0.0);
            for (i, node) in rows.chunks_exact(3 * modes).enumerate() {
                for (c, component) in node.chunks_exact(modes).enumerate() {
                    for (m, &value) in component.iter().enumerate() {
                        host[start + (3 * m + c) * len + i] = value;
                    }
                }
            }
        }
        let bytes = 4 * host.len() as u64;
        let limits = device.limits();
        let largest = limits.max_storage_buffer_binding_size.min(limits.max_buffer_size);
        if bytes > largest || host.len() > u32::MAX as usize {
            return Err(GpuError::Run(format!(
                "the bases need {bytes} bytes on the device; the adapter binds at most {largest}"
            )));
        }
        self.basis = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("basis"),
            contents: bytemuck::cast_slice(&host),
            usage: wgpu::BufferUsages::STORAGE,
        });
        self.basis_host = host;
        self.basis_starts.push(starts);
        self.rebind(device);
        Ok(self.basis_starts.len() - 1)
    }
}

fn bind(device: &wgpu::Device, pipeline: &wgpu::ComputePipeline, buffers: [&wgpu::Buffer; 5]) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry> = buffers
        .iter()
        .enumerate()
        .map(|(i, b)| wgpu::BindGroupEntry {
            binding: i as u32,
            resource: b.as_entire_binding(),
        })
        .collect();
    device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("kelvinlet field"),
        layout: &pipeline.get_bind_group_layout(0),
        entries: &entries,
    })
}
