//! A network served through ONNX Runtime under the model contract (docs/design.md §7), in either form:
//! `features` over every node, or `interaction` over the K interaction points alone (whose output is
//! the field itself or the coefficients of a [`Basis`] beside the graph).

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Instant;

use ort::session::Session;
use ort::session::builder::GraphOptimizationLevel;
use ort::value::TensorRef;

use super::basis::{self, Basis};
use super::manifest::{ForcesMode, Manifest, Mode, PriorModel};
use super::prior::ModelPrior;
use super::signature::{
    self, COEFFICIENTS, DISPLACEMENT, FORCES, INTERACTION_DEPTH_WIDTH, INTERACTION_GEOMETRY_WIDTH, INTERACTION_WIDTH,
    Input, Output, Signature,
};
use super::{LoadContext, ModelLoadError};
use crate::engine::{
    Answer, DeformationModel, Forces, ModelError, ModelInfo, ModelKind, StageTiming, Target, VOLUMETRIC_LAW_KEY,
};
use crate::fem::Stiffness;
use crate::mesh::TetMesh;
use crate::prior::gpu::{GpuBasis, GpuError, GpuPrior};
use crate::prior::{Coefficients, InteractionPoints, Kelvinlet, NodeCloud, Workspace};

/// Where a request runs on the GPU: the resident cloud, the basis beside it, and the Kelvinlet that
/// the same dispatch evaluates.
#[derive(Clone, Copy)]
struct GpuRequest<'a> {
    cloud: usize,
    basis: &'a GpuBasis,
    kelvinlet: &'a Kelvinlet,
}

/// A model directory's files, read: `manifest.toml`, `model.onnx` and, for graphs that output
/// coefficients, `basis.safetensors`.
#[derive(Clone, Copy)]
pub struct ModelFiles<'a> {
    pub manifest: &'a str,
    pub onnx: &'a [u8],
    pub basis: Option<&'a [u8]>,
}

/// Per-request buffers, pooled.
struct Buffers {
    /// `features` [N, C] row-major, positions filled once (features form); `interaction` [K, 6] or
    /// [K, 10] (interaction form).
    input: Vec<f32>,
    /// Nodes whose displacement/active channels the last request set, to clear them in O(K).
    dirty: Vec<u32>,
    /// [N, 3] prior over all nodes (models reading the prior only).
    prior: Vec<f32>,
    /// The network's share of the selected rows, for residual models that run beside the prior.
    network: Vec<f32>,
    /// The graph's `forces` output [K, 3], for graphs that give one.
    learned_forces: Vec<f32>,
    /// The prior's force on each interaction point (Green's-function priors).
    prior_forces: Vec<[f64; 3]>,
    workspace: Workspace,
}

pub struct OnnxModel {
    info: ModelInfo,
    mode: Mode,
    /// How a graph's `forces` output is served; `None` for graphs without one.
    forces: Option<ForcesMode>,
    signature: Signature,
    /// Φ for graphs whose output is `coefficients`.
    basis: Option<Basis>,
    /// The output the graph must give for one request, and its shape.
    output: (&'static str, Vec<i64>),
    /// Φ on the GPU the engine's clouds live on, once the engine attached one.
    gpu_basis: OnceLock<GpuBasis>,
    reads_prior: bool,
    channels: usize,
    node_count: usize,
    prior: ModelPrior,
    all_nodes: NodeCloud,
    /// `Session::run` needs exclusive access; one request at a time per model.
    session: Mutex<Session>,
    /// The features form's input with positions already written, to copy when the pool is empty.
    template: Vec<f32>,
    /// Each node's surface geometry, for interaction graphs that read it.
    geometry: Option<NodeGeometry>,
    pool: Mutex<Vec<Buffers>>,
}

impl OnnxModel {
    /// Loads `dir/model.onnx` (and `dir/basis.safetensors` if there is one) under `dir/manifest.toml`,
    /// validates them against `mesh`, warms up.
    pub fn load<'a>(dir: &Path, mesh: &TetMesh, context: impl Into<LoadContext<'a>>) -> Result<Self, ModelLoadError> {
        let read = |name: &str| {
            let path = dir.join(name);
            std::fs::read(&path).map_err(|e| ModelLoadError::new(&path.display().to_string(), e.to_string()))
        };
        let manifest = read("manifest.toml")?;
        let manifest = String::from_utf8(manifest)
            .map_err(|e| ModelLoadError::new(&dir.join("manifest.toml").display().to_string(), e.to_string()))?;
        let onnx = read("model.onnx")?;
        let basis = if dir.join(basis::FILE).exists() {
            Some(read(basis::FILE)?)
        } else {
            None
        };
        let files = ModelFiles {
            manifest: &manifest,
            onnx: &onnx,
            basis: basis.as_deref(),
        };
        Self::from_parts(&dir.display().to_string(), files, mesh, context)
    }

    /// Builds a model from its files' contents; `origin` names them in errors (`origin/manifest.toml`,
    /// `origin/model.onnx`, `origin/basis.safetensors`).
    pub fn from_parts<'a>(
        origin: &str,
        files: ModelFiles<'_>,
        mesh: &TetMesh,
        context: impl Into<LoadContext<'a>>,
    ) -> Result<Self, ModelLoadError> {
        let context = context.into();
        let manifest_path = format!("{origin}/manifest.toml");
        let manifest = Manifest::parse(files.manifest, &manifest_path)?;
        manifest.check_against(mesh, origin)?;
        let prior = model_prior(&manifest, context, &manifest_path)?;
        let onnx_path = format!("{origin}/model.onnx");
        let environment = super::runtime::environment(context.ort_dylib)?;
        // An interaction graph is a few small operators over K points: waking a second thread for
        // each (spinning is off, to leave the cores to the prior) costs more than it saves.
        let intra_threads = if manifest.reads_interaction() { 1 } else { threads() };
        let session = Session::builder(environment)
            .and_then(|b| {
                b.with_optimization_level(GraphOptimizationLevel::Level3)
                    .map_err(Into::into)
            })
            .and_then(|b| b.with_intra_threads(intra_threads).map_err(Into::into))
            .and_then(|b| b.with_intra_op_spinning(false).map_err(Into::into))
            .and_then(|mut b| b.commit_from_memory(files.onnx))
            .map_err(|e| ModelLoadError::new(&onnx_path, format!("ONNX Runtime cannot load it: {e}")))?;
        let n = mesh.node_count();
        let channels = manifest.channels();
        let signature = signature::read(&session, channels, n, &onnx_path)?;
        let declared = if manifest.reads_interaction() {
            Input::Interaction
        } else {
            Input::Features
        };
        if signature.input != declared {
            return Err(ModelLoadError::new(
                &manifest_path,
                format!(
                    "model.inputs = {:?} does not match the graph, whose input is {:?}",
                    manifest.model.inputs,
                    signature.input.name()
                ),
            ));
        }
        let forces = manifest.forces.as_ref().map(|f| f.mode);
        if signature.forces != forces.is_some() {
            let (graph, section) = if signature.forces {
                (
                    format!("gives {FORCES:?}"),
                    "has no [forces] section to say how they are served",
                )
            } else {
                (format!("has no {FORCES:?} output"), "has a [forces] section")
            };
            return Err(ModelLoadError::new(
                &manifest_path,
                format!("the graph {graph}, but the manifest {section}"),
            ));
        }
        let basis = load_basis(origin, files.basis, signature.output, mesh)?;
        let output = match &basis {
            Some(basis) => (COEFFICIENTS, vec![1, basis.modes() as i64]),
            None => (DISPLACEMENT, vec![1, n as i64, 3]),
        };

        let template = match signature.input {
            Input::Features => {
                let mut template = vec![0.0f32; n * channels];
                for (row, p) in template.chunks_exact_mut(channels).zip(&mesh.positions) {
                    for k in 0..3 {
                        row[k] = p[k] as f32;
                    }
                }
                template
            }
            Input::Interaction => Vec::new(),
        };
        let mut metadata: BTreeMap<String, String> = BTreeMap::new();
        metadata.insert("mode".into(), format!("{:?}", manifest.model.mode).to_lowercase());
        metadata.insert("method".into(), format!("{:?}", manifest.model.method).to_lowercase());
        let params = manifest.prior.kelvinlet();
        metadata.insert("prior.model".into(), prior.name().into());
        metadata.insert("prior.poisson_ratio".into(), params.poisson_ratio.to_string());
        metadata.insert("prior.epsilon_m".into(), params.epsilon.to_string());
        metadata.insert("prior.lambda".into(), params.lambda.to_string());
        metadata.insert("inputs".into(), format!("{:?}", manifest.model.inputs).to_lowercase());
        if let Some(basis) = &basis {
            metadata.insert("basis.modes".into(), basis.modes().to_string());
            metadata.insert("basis.precision".into(), basis.precision().into());
        }
        metadata.insert("description".into(), manifest.model.description.clone());
        if let Some(law) = manifest.volumetric_law() {
            metadata.insert(VOLUMETRIC_LAW_KEY.into(), law.name().into());
        }
        let no_metrics = BTreeMap::new();
        let force_metrics = manifest.forces.as_ref().map_or(&no_metrics, |f| &f.metrics);
        if let Some(mode) = forces {
            let text = match mode {
                ForcesMode::Residual => "learned: the prior's (G[S,S])⁻¹ u_S plus the network's force on each point",
                ForcesMode::Direct => "learned: the network's force on each interaction point",
            };
            metadata.insert("forces".into(), text.into());
        }
        for (section, values) in [
            ("metrics", &manifest.metrics),
            ("provenance", &manifest.provenance),
            ("forces", force_metrics),
        ] {
            for (k, v) in values {
                metadata.insert(format!("{section}.{k}"), v.to_string().trim_matches('"').to_owned());
            }
        }
        let model = OnnxModel {
            info: ModelInfo {
                name: manifest.model.name.clone(),
                kind: ModelKind::Neural,
                mesh: mesh.content_hash.clone(),
                regime: manifest.model.regime.clone(),
                metadata,
                // A field says nothing exact about the loads that hold it, and the prior's forces are
                // not the network's: only a graph trained on forces gives them.
                forces: if forces.is_some() {
                    Forces::Learned
                } else {
                    Forces::Unavailable
                },
            },
            mode: manifest.model.mode,
            forces,
            signature,
            basis,
            output,
            gpu_basis: OnceLock::new(),
            reads_prior: manifest.reads_prior(),
            channels,
            node_count: n,
            prior,
            all_nodes: NodeCloud::new(mesh.positions.iter().copied()),
            session: Mutex::new(session),
            template,
            geometry: signature.geometry.then(|| NodeGeometry::new(mesh, signature.depth)),
            pool: Mutex::new(Vec::new()),
        };
        model
            .warm_up(mesh)
            .map_err(|e| ModelLoadError::new(origin, format!("warm-up failed: {e}")))?;
        Ok(model)
    }

    /// One inference before the first client waits on it: allocates ONNX Runtime's arenas and checks
    /// the output's shape (on the rest state, or one surface node pulled 1 mm for the interaction form,
    /// which has no empty input).
    fn warm_up(&self, mesh: &TetMesh) -> Result<(), ModelError> {
        let mut buffers = self.take_buffers();
        let result = match self.signature.input {
            Input::Features => self.run_network(&buffers.input, 0, |_, _| Ok(())),
            Input::Interaction => {
                let mut points = InteractionPoints::default();
                let node = mesh.surface_nodes.first().copied().unwrap_or(0);
                points.push(node, mesh.positions[node as usize], [0.0, 0.0, 0.001]);
                fill_interaction(&points, self.geometry.as_ref(), &mut buffers.input);
                self.run_network(&buffers.input, 1, |_, _| Ok(()))
            }
        };
        buffers.dirty.clear();
        self.return_buffers(buffers);
        result
    }

    /// Whether the basis lives on a GPU, where requests over resident clouds add it in one dispatch.
    pub fn basis_on_gpu(&self) -> bool {
        self.gpu_basis.get().is_some()
    }

    fn take_buffers(&self) -> Buffers {
        let pooled = self.pool.lock().ok().and_then(|mut pool| pool.pop());
        pooled.unwrap_or_else(|| Buffers {
            input: self.template.clone(),
            dirty: Vec::new(),
            prior: if self.reads_prior {
                vec![0.0; 3 * self.node_count]
            } else {
                Vec::new()
            },
            network: Vec::new(),
            learned_forces: Vec::new(),
            prior_forces: Vec::new(),
            workspace: Workspace::default(),
        })
    }

    fn return_buffers(&self, buffers: Buffers) {
        if let Ok(mut pool) = self.pool.lock() {
            pool.push(buffers);
        }
    }

    /// Writes u_s and the active flag of the grasped nodes (and the prior, if read) into `features`.
    fn fill_features(&self, points: &InteractionPoints, buffers: &mut Buffers) {
        let c = self.channels;
        for &n in &buffers.dirty {
            buffers.input[n as usize * c + 3..n as usize * c + 7].fill(0.0);
        }
        buffers.dirty.clear();
        for (&n, u) in points.nodes.iter().zip(&points.displacements) {
            let row = &mut buffers.input[n as usize * c..(n as usize + 1) * c];
            row[3] = u[0] as f32;
            row[4] = u[1] as f32;
            row[5] = u[2] as f32;
            row[6] = 1.0;
            buffers.dirty.push(n);
        }
        if self.reads_prior {
            for (row, u) in buffers.input.chunks_exact_mut(c).zip(buffers.prior.chunks_exact(3)) {
                row[7..10].copy_from_slice(u);
            }
        }
    }

    /// Runs the session on `input` (`features` [1, N, C], or `interaction` [1, k, 6]) and hands the
    /// output's values, and the `forces` [1, k, 3] of a graph that gives them, to `consume`, after
    /// checking their shapes.
    fn run_network(
        &self,
        input: &[f32],
        k: usize,
        consume: impl FnOnce(&[f32], Option<&[f32]>) -> Result<(), ModelError>,
    ) -> Result<(), ModelError> {
        let name = self.signature.input.name();
        let shape = match self.signature.input {
            Input::Features => [1usize, self.node_count, self.channels],
            Input::Interaction => [1usize, k, self.signature.interaction_width()],
        };
        let tensor = TensorRef::from_array_view((shape, input))
            .map_err(|e| ModelError::Runtime(format!("cannot wrap the {name} input: {e}")))?;
        let mut session = self
            .session
            .lock()
            .map_err(|_| ModelError::Runtime("the session was poisoned by an earlier panic".into()))?;
        let outputs = session
            .run(ort::inputs![name => tensor])
            .map_err(|e| ModelError::Runtime(e.to_string()))?;
        let (output, expected) = &self.output;
        let (shape, values) = outputs[*output]
            .try_extract_tensor::<f32>()
            .map_err(|e| ModelError::Runtime(format!("output {output}: {e}")))?;
        if shape[..] != expected[..] {
            return Err(ModelError::Runtime(format!(
                "output {output} has shape {shape:?}, expected {expected:?}"
            )));
        }
        if !self.signature.forces {
            return consume(values, None);
        }
        let (shape, forces) = outputs[FORCES]
            .try_extract_tensor::<f32>()
            .map_err(|e| ModelError::Runtime(format!("output {FORCES}: {e}")))?;
        if shape[..] != [1, k as i64, 3] {
            return Err(ModelError::Runtime(format!(
                "output {FORCES} has shape {shape:?}, expected [1, {k}, 3]"
            )));
        }
        consume(values, Some(forces))
    }
}

/// The prior the manifest names; Green's functions come from `context`.
fn model_prior(manifest: &Manifest, context: LoadContext<'_>, origin: &str) -> Result<ModelPrior, ModelLoadError> {
    let stiffness = match manifest.prior.model {
        PriorModel::Kelvinlet => return Ok(ModelPrior::Kelvinlet(Kelvinlet::new(manifest.prior.kelvinlet()))),
        PriorModel::GreenLinear => Stiffness::Linear,
        PriorModel::GreenTangent => Stiffness::PreloadTangent,
    };
    let name = stiffness.model_name();
    let source = context.green.ok_or_else(|| {
        ModelLoadError::new(
            origin,
            format!(
                "prior.model = \"{name}\", but this loader has no Green's functions to give it (nak serve \
                 and nak eval build them when a model needs them)"
            ),
        )
    })?;
    let green = source(stiffness).map_err(|e| ModelLoadError::new(origin, format!("{name} prior: {e}")))?;
    Ok(ModelPrior::Green(green))
}

/// A graph outputs `coefficients` exactly when a basis lies beside it; the basis must fit the mesh and
/// the graph's M.
fn load_basis(
    origin: &str,
    bytes: Option<&[u8]>,
    output: Output,
    mesh: &TetMesh,
) -> Result<Option<Basis>, ModelLoadError> {
    let path = format!("{origin}/{}", basis::FILE);
    match (output, bytes) {
        (Output::Displacement, None) => Ok(None),
        (Output::Displacement, Some(_)) => Err(ModelLoadError::new(
            &path,
            format!(
                "a basis beside a graph whose output is {DISPLACEMENT:?}, not {COEFFICIENTS:?}: which one is meant?"
            ),
        )),
        (Output::Coefficients { .. }, None) => Err(ModelLoadError::new(
            &path,
            format!("missing: the graph outputs {COEFFICIENTS:?}, which need the basis they weigh"),
        )),
        (Output::Coefficients { modes }, Some(bytes)) => {
            let basis = Basis::parse(bytes, mesh, &path)?;
            if let Some(m) = modes.filter(|&m| m != basis.modes()) {
                return Err(ModelLoadError::new(
                    &path,
                    format!("has {} modes; the graph gives {m} coefficients", basis.modes()),
                ));
            }
            Ok(Some(basis))
        }
    }
}

/// Where an interaction graph's outputs are copied: its main output (g, or the field) and its forces.
struct Encoded<'a> {
    output: &'a mut Vec<f32>,
    forces: &'a mut Vec<f32>,
}

/// Writes each interaction point's rest position and prescribed displacement, [K, 6] row-major, and
/// with a `geometry` table the point's row of it after them, [K, 10] or [K, 11].
fn fill_interaction(points: &InteractionPoints, geometry: Option<&NodeGeometry>, input: &mut Vec<f32>) {
    input.clear();
    for ((p, u), &node) in points.positions.iter().zip(&points.displacements).zip(&points.nodes) {
        input.extend(p.iter().chain(u).map(|&v| v as f32));
        if let Some(geometry) = geometry {
            input.extend_from_slice(geometry.row(node));
        }
    }
}

/// Each node's surface geometry as an interaction graph reads it after the point's position and
/// displacement: its outward unit normal (zero inside) and lumped volume, then, for a graph that reads
/// it, the organ's depth beneath it (`TetMesh::inward_depths`).
struct NodeGeometry {
    values: Vec<f32>,
    width: usize,
}

impl NodeGeometry {
    fn new(mesh: &TetMesh, depth: bool) -> Self {
        let depths = if depth { mesh.inward_depths() } else { &[] };
        let width = if depth {
            INTERACTION_DEPTH_WIDTH
        } else {
            INTERACTION_GEOMETRY_WIDTH
        } - INTERACTION_WIDTH;
        let mut values = Vec::with_capacity(width * mesh.node_count());
        for (node, (n, &v)) in mesh.normals.iter().zip(&mesh.nodal_volumes).enumerate() {
            values.extend([n[0] as f32, n[1] as f32, n[2] as f32, v as f32]);
            values.extend(depths.get(node).map(|&d| d as f32));
        }
        Self { values, width }
    }

    /// Node `node`'s row; nodes were checked against the mesh when the request was resolved.
    fn row(&self, node: u32) -> &[f32] {
        let start = node as usize * self.width;
        debug_assert!(start + self.width <= self.values.len(), "node {node} outside the mesh");
        self.values.get(start..start + self.width).unwrap_or_default()
    }
}

/// Copies (or adds, with `add`) the rows of `target`'s nodes from a whole-mesh field [N, 3] into `out`.
fn gather(field: &[f32], target: Target<'_>, out: &mut [f32], add: bool) {
    let copy = |dst: &mut [f32], n: usize| {
        let src = &field[3 * n..3 * n + 3];
        for k in 0..3 {
            dst[k] = if add { dst[k] + src[k] } else { src[k] };
        }
    };
    match target.nodes {
        None => out.chunks_exact_mut(3).enumerate().for_each(|(n, dst)| copy(dst, n)),
        Some(nodes) => out
            .chunks_exact_mut(3)
            .zip(nodes)
            .for_each(|(dst, &n)| copy(dst, n as usize)),
    }
}

fn threads() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

impl DeformationModel for OnnxModel {
    fn info(&self) -> &ModelInfo {
        &self.info
    }

    fn attach_gpu(&self, gpu: &Arc<GpuPrior>, clouds: &[Option<&[u32]>]) -> Result<(), GpuError> {
        // Attached once: a second engine attaching the same model keeps the first upload. A model on
        // the green-linear prior keeps its basis on the CPU, where that prior is computed.
        let (Some(basis), None, Some(_)) = (&self.basis, self.gpu_basis.get(), self.prior.kelvinlet()) else {
            return Ok(());
        };
        let rows = clouds.iter().map(|nodes| basis.rows_f32(*nodes)).collect();
        let resident = gpu.upload_basis(rows, basis.modes())?;
        let _ = self.gpu_basis.set(resident);
        Ok(())
    }

    fn predict(
        &self,
        points: &InteractionPoints,
        target: Target<'_>,
        workspace: &mut Workspace,
        out: &mut Answer<'_>,
        timing: &mut StageTiming,
    ) -> Result<(), ModelError> {
        let mut buffers = self.take_buffers();
        let result = self
            .predict_with(points, target, workspace, &mut buffers, out.displacements, timing)
            .map(|()| self.write_forces(&buffers, out.forces));
        self.return_buffers(buffers);
        result
    }
}

impl OnnxModel {
    /// The force on each interaction point from the graph's `forces` output, plus the prior's own
    /// for `forces.mode = "residual"`.
    fn write_forces(&self, buffers: &Buffers, forces: &mut Vec<[f64; 3]>) {
        let Some(mode) = self.forces else {
            return;
        };
        forces.clear();
        let learned = buffers
            .learned_forces
            .chunks_exact(3)
            .map(|f| [f[0] as f64, f[1] as f64, f[2] as f64]);
        match mode {
            ForcesMode::Direct => forces.extend(learned),
            ForcesMode::Residual => forces.extend(
                buffers
                    .prior_forces
                    .iter()
                    .zip(learned)
                    .map(|(p, l)| std::array::from_fn(|k| p[k] + l[k])),
            ),
        }
    }

    fn predict_with(
        &self,
        points: &InteractionPoints,
        target: Target<'_>,
        workspace: &mut Workspace,
        buffers: &mut Buffers,
        out: &mut [f32],
        timing: &mut StageTiming,
    ) -> Result<(), ModelError> {
        match self.signature.input {
            Input::Features => self.predict_features(points, target, workspace, buffers, out, timing),
            Input::Interaction => self.predict_interaction(points, target, workspace, buffers, out, timing),
        }
    }

    /// The features form: the network sees every node, so its cost scales with N.
    fn predict_features(
        &self,
        points: &InteractionPoints,
        target: Target<'_>,
        workspace: &mut Workspace,
        buffers: &mut Buffers,
        out: &mut [f32],
        timing: &mut StageTiming,
    ) -> Result<(), ModelError> {
        if self.reads_prior {
            // The prior is an input: it must be ready, over every node, before the network runs.
            let start = Instant::now();
            let every_node = Target {
                cloud: &self.all_nodes,
                nodes: None,
            };
            timing.gpu = self.prior.field(
                points,
                every_node,
                &mut buffers.workspace,
                &mut buffers.prior,
                &mut buffers.prior_forces,
            )?;
            timing.prior_us = start.elapsed().as_secs_f32() * 1e6;
        }
        self.fill_features(points, buffers);
        let features = &buffers.input;
        let network = |out: &mut [f32], add: bool, network_us: &mut f32| {
            let start = Instant::now();
            let result = self.run_network(features, 0, |values, _| {
                gather(values, target, out, add);
                Ok(())
            });
            *network_us = start.elapsed().as_secs_f32() * 1e6;
            result
        };
        match self.mode {
            Mode::Direct => network(out, false, &mut timing.network_us),
            Mode::Residual if self.reads_prior => {
                gather(&buffers.prior, target, out, false);
                network(out, true, &mut timing.network_us)
            }
            Mode::Residual => {
                // Prior and network are independent: run them side by side, then add.
                let mut network_out = std::mem::take(&mut buffers.network);
                network_out.resize(out.len(), 0.0);
                let mut network_us = 0.0;
                let mut prior_us = 0.0;
                let prior_forces = &mut buffers.prior_forces;
                let (prior, net) = rayon::join(
                    || {
                        let start = Instant::now();
                        let r = self.prior.field(points, target, workspace, out, prior_forces);
                        prior_us = start.elapsed().as_secs_f32() * 1e6;
                        r
                    },
                    || network(&mut network_out, false, &mut network_us),
                );
                for (o, r) in out.iter_mut().zip(&network_out) {
                    *o += r;
                }
                buffers.network = network_out;
                timing.gpu = prior?;
                net?;
                timing.prior_us = prior_us;
                timing.network_us = network_us;
                Ok(())
            }
        }
    }

    /// The interaction form: the network sees only the K points; the field is its output, or Φ g.
    /// In residual mode the network runs beside the prior and its share is added once both are done.
    fn predict_interaction(
        &self,
        points: &InteractionPoints,
        target: Target<'_>,
        workspace: &mut Workspace,
        buffers: &mut Buffers,
        out: &mut [f32],
        timing: &mut StageTiming,
    ) -> Result<(), ModelError> {
        if let Some(gpu_basis) = self.gpu_basis.get()
            && let Some(resident) = target.cloud.resident()
            && gpu_basis.lives_on(&resident.gpu)
            && let Some(kelvinlet) = self.prior.kelvinlet()
        {
            let on_gpu = GpuRequest {
                cloud: resident.cloud,
                basis: gpu_basis,
                kelvinlet,
            };
            match self.predict_on_gpu(points, on_gpu, workspace, buffers, out, timing) {
                Ok(()) => return Ok(()),
                // The answer is still owed: the CPU gives the same field, a little later.
                Err(e) => tracing::warn!(model = %self.info.name, "GPU failed, this request runs on the CPU: {e}"),
            }
        }
        // The encoder (ONNX Runtime, one thread) runs beside the prior (the rayon pool); the network's
        // share is added once both are done, while the pool's threads are still awake.
        let Buffers {
            input,
            network,
            learned_forces,
            prior_forces,
            ..
        } = buffers;
        let mut encoder_us = 0.0;
        let mut encoded = Encoded {
            output: network,
            forces: learned_forces,
        };
        let (prior, encoded_result) = match self.mode {
            Mode::Residual => rayon::join(
                || {
                    let start = Instant::now();
                    let result = self.prior.field(points, target, workspace, out, prior_forces);
                    timing.prior_us = start.elapsed().as_secs_f32() * 1e6;
                    result.map(|gpu| timing.gpu = gpu)
                },
                || self.encode(points, input, &mut encoded, &mut encoder_us),
            ),
            Mode::Direct => {
                out.fill(0.0);
                (Ok(()), self.encode(points, input, &mut encoded, &mut encoder_us))
            }
        };
        let network: &[f32] = encoded.output;
        let start = Instant::now();
        let result = prior.and(encoded_result).map(|()| match &self.basis {
            Some(basis) => basis.add_product(network, target.nodes, out),
            None => gather(network, target, out, true),
        });
        timing.network_us = encoder_us + start.elapsed().as_secs_f32() * 1e6;
        result
    }

    /// Runs an interaction graph on `points` and copies its outputs (g, or the whole field; the
    /// forces of a graph that gives them) into `into`, timing it into `elapsed_us`.
    fn encode(
        &self,
        points: &InteractionPoints,
        input: &mut Vec<f32>,
        into: &mut Encoded<'_>,
        elapsed_us: &mut f32,
    ) -> Result<(), ModelError> {
        let start = Instant::now();
        fill_interaction(points, self.geometry.as_ref(), input);
        let result = self.run_network(input, points.len(), |values, forces| {
            into.output.clear();
            into.output.extend_from_slice(values);
            into.forces.clear();
            into.forces.extend_from_slice(forces.unwrap_or_default());
            Ok(())
        });
        *elapsed_us = start.elapsed().as_secs_f32() * 1e6;
        result
    }

    /// The interaction form with Φ on the GPU: the network gives g on the CPU, then one dispatch
    /// evaluates prior and residual together over resident cloud `cloud`, `Σ_j Γ_j k_j + Φ g`
    /// (docs/design.md §7). `prior_us` is the solve and that dispatch; `network_us` the encoder.
    fn predict_on_gpu(
        &self,
        points: &InteractionPoints,
        GpuRequest {
            cloud,
            basis,
            kelvinlet,
        }: GpuRequest<'_>,
        workspace: &mut Workspace,
        buffers: &mut Buffers,
        out: &mut [f32],
        timing: &mut StageTiming,
    ) -> Result<(), ModelError> {
        let mut encoded = Encoded {
            output: &mut buffers.network,
            forces: &mut buffers.learned_forces,
        };
        self.encode(points, &mut buffers.input, &mut encoded, &mut timing.network_us)?;
        let start = Instant::now();
        let empty = Coefficients::default();
        let coefficients = match self.mode {
            Mode::Residual => {
                kelvinlet.solve(points, workspace)?;
                &workspace.coefficients
            }
            Mode::Direct => &empty,
        };
        let phases = basis
            .gpu()
            .evaluate_with_basis(kelvinlet, cloud, coefficients, basis, &buffers.network, out)
            .map_err(|e| ModelError::Runtime(e.to_string()))?;
        timing.prior_us = start.elapsed().as_secs_f32() * 1e6;
        timing.gpu = Some(phases);
        Ok(())
    }
}
