//! The Kelvinlet field on the GPU (wgpu, WGSL kernel `field.wgsl`).
//!
//! Node clouds are uploaded once into one persistent buffer. A request sends only its K points and
//! coefficients (32 bytes each) and reads back its (N, 3) field. One worker thread owns the device:
//! requests that arrive while it is busy are batched into a single dispatch (workgroup row = request),
//! up to [`MAX_BATCH`]. The (3K)×(3K) solve stays on the CPU in f64: for K ≤ 256 it takes
//! microseconds, less than one GPU round trip, and f32 on the GPU would cost accuracy.

use std::sync::mpsc::{self, Receiver, Sender, SyncSender};
use std::sync::{Arc, Mutex, OnceLock};

use wgpu::util::DeviceExt;

use super::kernel::BLOCK;
use super::{Coefficients, Kelvinlet, NodeCloud};

/// Requests served by one dispatch at most.
pub const MAX_BATCH: usize = 32;
const WORKGROUP: u32 = 64;

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
    #[error("the GPU worker has stopped")]
    Stopped,
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

struct Submission {
    jobs: Vec<Job>,
    reply: SyncSender<Result<Vec<Vec<f32>>, GpuError>>,
}

/// A basis to keep on the device: its rows [len, 3, M] for each resident cloud, in cloud order.
struct Upload {
    per_cloud: Vec<Vec<f32>>,
    reply: SyncSender<Result<usize, GpuError>>,
}

enum Message {
    Evaluate(Submission),
    Upload(Upload),
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

/// A handle to the GPU worker; cheap to share.
pub struct GpuPrior {
    sender: Mutex<Sender<Message>>,
    adapter: String,
    clouds: Vec<usize>,
}

impl std::fmt::Debug for GpuPrior {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuPrior").field("adapter", &self.adapter).finish()
    }
}

/// Where a node cloud lives on the GPU.
#[derive(Clone, Debug)]
pub struct Resident {
    pub gpu: Arc<GpuPrior>,
    pub cloud: usize,
}

impl PartialEq for Resident {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.gpu, &other.gpu) && self.cloud == other.cloud
    }
}

/// The process's one wgpu instance, never dropped. Dropping the last handle to it unloads the Vulkan
/// driver (`dlclose`), but Mesa's software drivers (llvmpipe/lavapipe, and the LLVM inside them)
/// register `atexit` destructors: a process whose GPU worker released the device just before `exit`
/// then crashed in those handlers (seen in CI as a segfault after a successful `nak predict`).
fn process_instance() -> &'static wgpu::Instance {
    static INSTANCE: OnceLock<wgpu::Instance> = OnceLock::new();
    INSTANCE.get_or_init(|| wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env()))
}

impl GpuPrior {
    /// Opens the first GPU adapter wgpu finds and uploads `clouds`; their indices identify them later.
    pub fn new(clouds: &[&NodeCloud]) -> Result<Arc<Self>, GpuError> {
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
        let worker = Worker::new(device, queue, clouds, &limits);
        let (sender, receiver) = mpsc::channel();
        std::thread::Builder::new()
            .name("nak-gpu".into())
            .spawn(move || worker.serve(receiver))
            .map_err(|e| GpuError::Run(e.to_string()))?;
        tracing::info!(adapter = %name, clouds = clouds.len(), "GPU prior ready");
        Ok(Arc::new(Self {
            sender: Mutex::new(sender),
            adapter: name,
            clouds: clouds.iter().map(|c| c.len()).collect(),
        }))
    }

    pub fn adapter(&self) -> &str {
        &self.adapter
    }

    fn send(&self, message: Message) -> Result<(), GpuError> {
        self.sender
            .lock()
            .map_err(|_| GpuError::Stopped)?
            .send(message)
            .map_err(|_| GpuError::Stopped)
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

    fn submit(&self, jobs: Vec<Job>) -> Result<Vec<Vec<f32>>, GpuError> {
        let (reply, answer) = mpsc::sync_channel(1);
        self.send(Message::Evaluate(Submission { jobs, reply }))?;
        answer.recv().map_err(|_| GpuError::Stopped)?
    }

    /// Evaluates several requests in one dispatch; each is (cloud index, coefficients).
    pub fn evaluate_batch(
        &self,
        kelvinlet: &Kelvinlet,
        requests: &[(usize, &Coefficients)],
    ) -> Result<Vec<Vec<f32>>, GpuError> {
        let jobs = requests
            .iter()
            .map(|&(cloud, c)| Self::job(kelvinlet, cloud, c, None))
            .collect();
        self.submit(jobs)
    }

    /// Writes the field of `coefficients` over resident cloud `cloud` into `out` ((N, 3) rows).
    pub fn evaluate(
        &self,
        kelvinlet: &Kelvinlet,
        cloud: usize,
        coefficients: &Coefficients,
        out: &mut [f32],
    ) -> Result<(), GpuError> {
        self.evaluate_into(Self::job(kelvinlet, cloud, coefficients, None), out)
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
    ) -> Result<(), GpuError> {
        if g.len() != basis.modes {
            return Err(GpuError::Run(format!(
                "{} coefficients for a basis of {} modes",
                g.len(),
                basis.modes
            )));
        }
        self.evaluate_into(
            Self::job(kelvinlet, cloud, coefficients, Some((basis.id, g.to_vec()))),
            out,
        )
    }

    fn evaluate_into(&self, job: Job, out: &mut [f32]) -> Result<(), GpuError> {
        let cloud = job.cloud;
        if out.len() != 3 * self.clouds.get(cloud).copied().unwrap_or(usize::MAX) {
            return Err(GpuError::Run(format!(
                "output of {} values for cloud {cloud}",
                out.len()
            )));
        }
        let mut fields = self.submit(vec![job])?;
        out.copy_from_slice(&fields.pop().unwrap_or_default());
        Ok(())
    }

    /// Keeps a basis on the device: `per_cloud[c]` is Φ's rows [len_c, 3, M] for resident cloud `c`.
    pub fn upload_basis(self: &Arc<Self>, per_cloud: Vec<Vec<f32>>, modes: usize) -> Result<GpuBasis, GpuError> {
        let fits = per_cloud.len() == self.clouds.len()
            && per_cloud
                .iter()
                .zip(&self.clouds)
                .all(|(rows, &len)| rows.len() == 3 * len * modes);
        if !fits || modes == 0 {
            return Err(GpuError::Run(format!(
                "a basis of {modes} modes whose rows do not match the resident clouds {:?}",
                self.clouds
            )));
        }
        let (reply, answer) = mpsc::sync_channel(1);
        self.send(Message::Upload(Upload { per_cloud, reply }))?;
        let id = answer.recv().map_err(|_| GpuError::Stopped)??;
        Ok(GpuBasis {
            gpu: self.clone(),
            id,
            modes,
        })
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

struct Worker {
    device: wgpu::Device,
    queue: wgpu::Queue,
    pipeline: wgpu::ComputePipeline,
    positions: wgpu::Buffer,
    /// (offset, length) of each cloud in `positions`, in nodes.
    clouds: Vec<(usize, usize)>,
    points: wgpu::Buffer,
    jobs: wgpu::Buffer,
    field: wgpu::Buffer,
    staging: wgpu::Buffer,
    /// Every uploaded basis, one after another; `bases[id][cloud]` is where a cloud's rows start.
    basis: wgpu::Buffer,
    basis_host: Vec<f32>,
    bases: Vec<Vec<usize>>,
    bind_group: wgpu::BindGroup,
    capacity: usize,
}

impl Worker {
    fn new(device: wgpu::Device, queue: wgpu::Queue, clouds: &[&NodeCloud], limits: &wgpu::Limits) -> Self {
        let mut positions = Vec::new();
        let mut ranges = Vec::with_capacity(clouds.len());
        for cloud in clouds {
            ranges.push((positions.len(), cloud.len()));
            positions.extend((0..cloud.len()).map(|i| {
                let p = cloud.position(i / BLOCK, i % BLOCK);
                [p[0], p[1], p[2], 0.0f32]
            }));
        }
        if positions.is_empty() {
            positions.push([0.0; 4]);
        }
        let positions = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("node positions"),
            contents: bytemuck::cast_slice(&positions),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let largest = ranges.iter().map(|r| r.1).max().unwrap_or(1).max(1);
        let binding = limits.max_storage_buffer_binding_size.min(limits.max_buffer_size) as usize;
        let capacity = (binding / (12 * largest)).clamp(1, MAX_BATCH);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("field.wgsl"),
            source: wgpu::ShaderSource::Wgsl(include_str!("field.wgsl").into()),
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("kelvinlet field"),
            layout: None,
            module: &module,
            entry_point: Some("main"),
            compilation_options: Default::default(),
            cache: None,
        });
        let storage = |label, size: usize, usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: size.max(16) as u64,
                usage,
                mapped_at_creation: false,
            })
        };
        let copy_in = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        let field_size = 12 * largest * capacity;
        let points = storage("points", 32 * 256 * capacity, copy_in);
        let jobs = storage("jobs", std::mem::size_of::<JobEntry>() * capacity, copy_in);
        let field = storage(
            "field",
            field_size,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        );
        let staging = storage(
            "readback",
            field_size,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        );
        let basis = storage("basis", 16, copy_in);
        let bind_group = Self::bind(&device, &pipeline, [&positions, &points, &jobs, &field, &basis]);
        Self {
            device,
            queue,
            pipeline,
            positions,
            clouds: ranges,
            points,
            jobs,
            field,
            staging,
            basis,
            basis_host: Vec::new(),
            bases: Vec::new(),
            bind_group,
            capacity,
        }
    }

    fn rebind(&mut self) {
        self.bind_group = Self::bind(
            &self.device,
            &self.pipeline,
            [&self.positions, &self.points, &self.jobs, &self.field, &self.basis],
        );
    }

    /// Appends a basis to the device's basis buffer (rebuilt whole: uploads happen at load, not per
    /// request) and returns its id.
    fn upload(&mut self, upload: Upload) -> Result<usize, GpuError> {
        let mut starts = Vec::with_capacity(upload.per_cloud.len());
        let mut host = self.basis_host.clone();
        for rows in &upload.per_cloud {
            starts.push(host.len());
            host.extend_from_slice(rows);
        }
        let bytes = 4 * host.len() as u64;
        let limits = self.device.limits();
        let largest = limits.max_storage_buffer_binding_size.min(limits.max_buffer_size);
        if bytes > largest || host.len() > u32::MAX as usize {
            return Err(GpuError::Run(format!(
                "the bases need {bytes} bytes on the device; the adapter binds at most {largest}"
            )));
        }
        self.basis = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("basis"),
            contents: bytemuck::cast_slice(&host),
            usage: wgpu::BufferUsages::STORAGE,
        });
        self.basis_host = host;
        self.bases.push(starts);
        self.rebind();
        Ok(self.bases.len() - 1)
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

    /// Takes submissions as they come; whatever queued up meanwhile joins the next dispatch.
    fn serve(mut self, receiver: Receiver<Message>) {
        let mut pending = None;
        loop {
            let first = match pending.take().map_or_else(|| receiver.recv(), Ok) {
                Ok(Message::Evaluate(s)) => s,
                Ok(Message::Upload(upload)) => {
                    let reply = upload.reply.clone();
                    let _ = reply.send(self.upload(upload));
                    continue;
                }
                Err(_) => return,
            };
            let mut batch = vec![first];
            let mut jobs = batch[0].jobs.len();
            while jobs < self.capacity {
                match receiver.try_recv() {
                    Ok(Message::Evaluate(s)) => {
                        jobs += s.jobs.len();
                        batch.push(s);
                    }
                    // An upload waits for the dispatch gathered so far.
                    Ok(upload) => {
                        pending = Some(upload);
                        break;
                    }
                    Err(_) => break,
                }
            }
            let all: Vec<&Job> = batch.iter().flat_map(|s| &s.jobs).collect();
            let mut fields = Vec::with_capacity(all.len());
            let mut failure = None;
            for group in all.chunks(self.capacity) {
                match self.run(group) {
                    Ok(f) => fields.extend(f),
                    Err(e) => {
                        failure = Some(e);
                        break;
                    }
                }
            }
            let mut fields = fields.into_iter();
            for s in batch {
                let answer = match &failure {
                    Some(e) => Err(e.clone()),
                    None => Ok(fields.by_ref().take(s.jobs.len()).collect()),
                };
                // A requester that gave up is no reason to stop serving the others.
                let _ = s.reply.send(answer);
            }
        }
    }

    fn run(&mut self, jobs: &[&Job]) -> Result<Vec<Vec<f32>>, GpuError> {
        let mut entries = Vec::with_capacity(jobs.len());
        let mut points: Vec<[f32; 8]> = Vec::new();
        let mut out = 0usize;
        for job in jobs {
            let &(offset, len) = self
                .clouds
                .get(job.cloud)
                .ok_or_else(|| GpuError::Run(format!("no resident cloud {}", job.cloud)))?;
            let point_offset = points.len();
            points.extend_from_slice(&job.points);
            let (modes, basis_offset, coefficient_offset) = match &job.basis {
                None => (0, 0, 0),
                Some((id, g)) => {
                    let start = self
                        .bases
                        .get(*id)
                        .and_then(|b| b.get(job.cloud))
                        .ok_or_else(|| GpuError::Run(format!("no resident basis {id}")))?;
                    // g rides in the points buffer, 8 floats (two vec4s) per entry.
                    let at = 2 * points.len();
                    points.extend(
                        g.chunks(8)
                            .map(|c| std::array::from_fn(|i| c.get(i).copied().unwrap_or(0.0))),
                    );
                    (g.len() as u32, *start as u32, at as u32)
                }
            };
            entries.push(JobEntry {
                cloud_offset: offset as u32,
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
            out += 3 * len;
        }
        let point_bytes = (32 * points.len()) as u64;
        if point_bytes > self.points.size() {
            self.points = self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("points"),
                size: point_bytes.next_power_of_two(),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            self.rebind();
        }
        if !points.is_empty() {
            self.queue.write_buffer(&self.points, 0, bytemuck::cast_slice(&points));
        }
        self.queue.write_buffer(&self.jobs, 0, bytemuck::cast_slice(&entries));
        let widest = entries.iter().map(|e| e.cloud_len).max().unwrap_or(0);
        let bytes = (4 * out) as u64;
        let mut encoder = self.device.create_command_encoder(&Default::default());
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &self.bind_group, &[]);
            pass.dispatch_workgroups(widest.div_ceil(WORKGROUP), entries.len() as u32, 1);
        }
        if bytes > 0 {
            encoder.copy_buffer_to_buffer(&self.field, 0, &self.staging, 0, bytes);
        }
        let submission = self.queue.submit([encoder.finish()]);
        if bytes == 0 {
            return Ok(jobs.iter().map(|_| Vec::new()).collect());
        }
        let slice = self.staging.slice(..bytes);
        let (mapped, done) = mpsc::sync_channel(1);
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = mapped.send(r);
        });
        self.device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(submission),
                timeout: None,
            })
            .map_err(|e| GpuError::Run(e.to_string()))?;
        done.recv()
            .map_err(|_| GpuError::Stopped)?
            .map_err(|e| GpuError::Run(e.to_string()))?;
        let fields = {
            let view = slice.get_mapped_range().map_err(|e| GpuError::Run(e.to_string()))?;
            let values: &[f32] = bytemuck::cast_slice(&view);
            entries
                .iter()
                .map(|e| values[e.out_offset as usize..e.out_offset as usize + 3 * e.cloud_len as usize].to_vec())
                .collect()
        };
        self.staging.unmap();
        Ok(fields)
    }
}
