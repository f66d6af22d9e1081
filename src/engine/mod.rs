//! The prediction engine: validates a request, resolves its grasps, runs the model, and returns the
//! displacements of the selected nodes. `nak serve` and `nak predict` both go through it.

pub mod grasp;
mod held;
pub mod model;
pub mod regime;

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;

pub use grasp::Grasp;
pub use held::HELD_NODES;
pub use model::{
    Answer, DeformationModel, Forces, KelvinletModel, ModelError, ModelInfo, ModelKind, StageTiming, Target,
    VOLUMETRIC_LAW_KEY,
};
pub use regime::Regime;

use crate::mesh::TetMesh;
use crate::prior::gpu::GpuError;
use crate::prior::{GpuPhases, InteractionPoints, Kelvinlet, NodeCloud, PriorBackend, Workspace, backend};

/// What the server accepts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Limits {
    /// Largest grasp displacement magnitude (metres).
    pub max_displacement_m: f64,
    /// Most interaction points (grasped nodes) in one request.
    pub max_interaction_points: usize,
    /// Node–point pairs up to which a prior-only request is quick ([`Engine::is_quick`]); 0: none is.
    pub quick_terms: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_displacement_m: 0.2,
            max_interaction_points: 256,
            quick_terms: QUICK_TERMS,
        }
    }
}

/// Why a request was refused; [`EngineError::kind`] maps it onto a gRPC status code.
#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    #[error("{0}")]
    NotFound(String),
    #[error("{0}")]
    InvalidArgument(String),
    #[error("model {model} failed: {source}")]
    Model {
        model: String,
        #[source]
        source: ModelError,
    },
}

impl EngineError {
    pub fn invalid(message: impl Into<String>) -> Self {
        EngineError::InvalidArgument(message.into())
    }
}

/// Which nodes a prediction answers for.
#[derive(Debug, Clone, PartialEq, Default)]
pub enum Selection {
    #[default]
    All,
    Surface,
    List(Vec<u32>),
}

/// One prediction request, independent of the wire format.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Request {
    /// Empty means the engine's default model ([`Engine::default_model`]).
    pub model: String,
    /// Name or content hash of the mesh the client expects; empty means the served mesh.
    pub mesh: String,
    pub grasps: Vec<Grasp>,
    pub selection: Selection,
}

/// Microseconds per stage of one prediction.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Timing {
    pub resolve_us: f32,
    /// Between [`Engine::prepare`] and [`Engine::compute`]: waiting for a compute thread.
    pub queue_us: f32,
    pub prior_us: f32,
    pub network_us: f32,
    pub total_us: f32,
    /// Where the prior's time went, when its field was evaluated on the GPU.
    pub gpu: Option<GpuPhases>,
}

/// The default [`Limits::quick_terms`]: about 150 µs of field on one core of the machine in
/// docs/reports/latency.md, the phantom (9,701 nodes) with up to 54 interaction points.
pub const QUICK_TERMS: usize = 1 << 19;

/// A request checked and with its grasps resolved, ready for [`Engine::compute`] on any thread.
pub struct Prepared {
    model: Arc<dyn DeformationModel>,
    scratch: Scratch,
    start: Instant,
    resolved: Instant,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Prediction {
    pub model: String,
    /// Row-major (n, 3) f32 displacements of the selected nodes.
    pub displacements: Vec<f32>,
    /// The node of each row, unless the selection was every node.
    pub node_ids: Option<Vec<u32>>,
    pub interaction_points: usize,
    /// Per grasp, the force (N) the grasper exerts on the tissue, when the model gives forces.
    pub grasp_forces: Option<Vec<[f64; 3]>>,
    pub timing: Timing,
}

/// Per-request scratch buffers, pooled so that steady-state requests allocate only their response.
#[derive(Default)]
struct Scratch {
    points: InteractionPoints,
    workspace: Workspace,
    point_forces: Vec<[f64; 3]>,
    held_by_node: Vec<(u32, usize)>,
}

/// A model the server was asked to serve but could not load, and why (`GetStatus` lists them).
#[derive(Debug, Clone, PartialEq)]
pub struct RefusedModel {
    /// The file or directory at fault.
    pub origin: String,
    pub reason: String,
}

pub struct Engine {
    mesh: Arc<TetMesh>,
    limits: Limits,
    models: BTreeMap<String, Arc<dyn DeformationModel>>,
    /// The model a request that names none gets.
    default_model: String,
    refused: Vec<RefusedModel>,
    all_nodes: NodeCloud,
    surface_nodes: NodeCloud,
    scratch: Mutex<Vec<Scratch>>,
}

impl Engine {
    /// An engine serving `mesh` with the Kelvinlet prior.
    pub fn new(mesh: Arc<TetMesh>, limits: Limits) -> Self {
        let all_nodes = NodeCloud::new(mesh.positions.iter().copied());
        let surface_nodes = NodeCloud::new(mesh.surface_nodes.iter().map(|&n| mesh.positions[n as usize]));
        let kelvinlet: Arc<dyn DeformationModel> = Arc::new(KelvinletModel::new(&mesh));
        Self {
            models: BTreeMap::from([(KelvinletModel::NAME.to_owned(), kelvinlet)]),
            default_model: KelvinletModel::NAME.to_owned(),
            refused: Vec::new(),
            mesh,
            limits,
            all_nodes,
            surface_nodes,
            scratch: Mutex::new(Vec::new()),
        }
    }

    /// Evaluates the prior of whole-mesh and surface requests on `backend` (`auto` decides for each
    /// of the two; listed node subsets stay on the CPU: they are small and change per request).
    /// Returns what was chosen and why.
    /// Models added before or after move their own mesh-sized data to the GPU too.
    pub fn use_prior_backend(&mut self, backend: PriorBackend) -> Result<String, GpuError> {
        let kelvinlet = Kelvinlet::new(self.mesh.config.prior);
        let choice = backend::attach(
            backend,
            &kelvinlet,
            &mut [("all nodes", &mut self.all_nodes), ("surface", &mut self.surface_nodes)],
        )?;
        for model in self.models.values() {
            self.attach_to_gpu(model.as_ref());
        }
        Ok(choice)
    }

    /// Serves `model` beside the others; a model of the same name is replaced.
    pub fn add_model(&mut self, model: Arc<dyn DeformationModel>) {
        self.attach_to_gpu(model.as_ref());
        self.models.insert(model.info().name.clone(), model);
    }

    /// Lets `model` upload its data to the GPU the clouds live on (in the order
    /// [`Self::use_prior_backend`] uploaded them); a failure leaves it on the CPU.
    fn attach_to_gpu(&self, model: &dyn DeformationModel) {
        let Some(resident) = self.all_nodes.resident().or(self.surface_nodes.resident()) else {
            return;
        };
        let clouds = [None, Some(&self.mesh.surface_nodes[..])];
        if let Err(e) = model.attach_gpu(&resident.gpu, &clouds) {
            tracing::warn!(model = %model.info().name, "stays on the CPU: {e}");
        }
    }

    pub fn mesh(&self) -> &Arc<TetMesh> {
        &self.mesh
    }

    pub fn limits(&self) -> Limits {
        self.limits
    }

    pub fn models(&self) -> impl Iterator<Item = &ModelInfo> {
        self.models.values().map(|m| m.info())
    }

    /// The model a request naming none gets: the Kelvinlet unless [`Self::default_to_most_accurate`]
    /// chose another.
    pub fn default_model(&self) -> &str {
        &self.default_model
    }

    /// The model that answers a request for `requested` (empty: the default).
    pub fn resolve_model_name<'a>(&'a self, requested: &'a str) -> &'a str {
        if requested.is_empty() {
            &self.default_model
        } else {
            requested
        }
    }

    /// Makes the most accurate model of `regime` served now ([`regime::most_accurate`]) the default,
    /// and returns its name; refused, with what is served, when no model of the regime qualifies.
    pub fn default_to_most_accurate(&mut self, regime: Regime) -> Result<&str, EngineError> {
        let best = regime::most_accurate(self.models(), regime).map(|info| info.name.clone());
        let Some(best) = best else {
            let served: Vec<String> = self
                .models()
                .map(|m| match m.regime.as_str() {
                    "" => m.name.clone(),
                    regime => format!("{} ({regime})", m.name),
                })
                .collect();
            return Err(EngineError::NotFound(format!(
                "no {regime} model with a held-out DCM in its manifest is served{}; served: {}",
                match regime {
                    Regime::Linear => " and green-linear is not",
                    Regime::Nonlinear => "",
                },
                served.join(", ")
            )));
        };
        self.default_model = best;
        Ok(&self.default_model)
    }

    /// Notes a model that could not be loaded; the others are served.
    pub fn refuse_model(&mut self, refused: RefusedModel) {
        self.refused.push(refused);
    }

    pub fn refused_models(&self) -> &[RefusedModel] {
        &self.refused
    }

    /// Whether `name` (a mesh name or content hash) is the served mesh; empty always is.
    pub fn serves_mesh(&self, name: &str) -> bool {
        name.is_empty() || name == self.mesh.config.name || name == self.mesh.content_hash
    }

    pub fn predict(&self, request: &Request) -> Result<Prediction, EngineError> {
        let prepared = self.prepare(request)?;
        self.compute(prepared, request)
    }

    /// Checks the mesh and the model and resolves the grasps to interaction points: microseconds,
    /// and enough to tell how much work the rest is ([`Self::is_quick`]).
    pub fn prepare(&self, request: &Request) -> Result<Prepared, EngineError> {
        let start = Instant::now();
        if !self.serves_mesh(&request.mesh) {
            return Err(EngineError::NotFound(format!(
                "mesh {:?} is not served here; this server serves {:?} ({})",
                request.mesh, self.mesh.config.name, self.mesh.content_hash
            )));
        }
        let name = self.resolve_model_name(&request.model);
        let model = self.models.get(name).ok_or_else(|| {
            EngineError::NotFound(format!(
                "unknown model {name:?}; available: {}",
                self.models.keys().cloned().collect::<Vec<_>>().join(", ")
            ))
        })?;
        let mut scratch = self.take_scratch();
        if let Err(e) = grasp::resolve(&self.mesh, &self.limits, &request.grasps, &mut scratch.points) {
            self.return_scratch(scratch);
            return Err(e);
        }
        Ok(Prepared {
            model: model.clone(),
            scratch,
            start,
            resolved: Instant::now(),
        })
    }

    /// Whether computing `prepared` costs less than handing it to another thread and back: a prior
    /// alone (no network, no solve over the mesh) over at most [`Limits::quick_terms`] node–point
    /// pairs.
    pub fn is_quick(&self, prepared: &Prepared, request: &Request) -> bool {
        let nodes = match &request.selection {
            Selection::All => self.mesh.node_count(),
            Selection::Surface => self.mesh.surface_nodes.len(),
            Selection::List(nodes) => nodes.len(),
        };
        prepared.model.info().kind == ModelKind::Prior
            && nodes.saturating_mul(prepared.scratch.points.len()) <= self.limits.quick_terms
    }

    /// Runs the model of a request [`Self::prepare`]d, on whatever thread calls it.
    pub fn compute(&self, prepared: Prepared, request: &Request) -> Result<Prediction, EngineError> {
        let Prepared {
            model,
            mut scratch,
            start,
            resolved,
        } = prepared;
        let result = self.run(model.as_ref(), request, &mut scratch, start, resolved);
        self.return_scratch(scratch);
        result
    }

    fn run(
        &self,
        model: &dyn DeformationModel,
        request: &Request,
        scratch: &mut Scratch,
        start: Instant,
        resolved: Instant,
    ) -> Result<Prediction, EngineError> {
        let computing = Instant::now();
        let n = self.mesh.node_count();
        let listed;
        let target = match &request.selection {
            Selection::All => Target {
                cloud: &self.all_nodes,
                nodes: None,
            },
            Selection::Surface => Target {
                cloud: &self.surface_nodes,
                nodes: Some(&self.mesh.surface_nodes),
            },
            Selection::List(nodes) => {
                if nodes.is_empty() {
                    return Err(EngineError::invalid("the node selection is an empty list"));
                }
                if let Some(bad) = nodes.iter().find(|&&v| v as usize >= n) {
                    return Err(EngineError::invalid(format!(
                        "selected node {bad} does not exist: the mesh has {n} nodes"
                    )));
                }
                listed = NodeCloud::new(nodes.iter().map(|&v| self.mesh.positions[v as usize]));
                Target {
                    cloud: &listed,
                    nodes: Some(nodes),
                }
            }
        };
        let mut displacements = vec![0.0f32; 3 * target.cloud.len()];
        let mut stages = StageTiming::default();
        scratch.point_forces.clear();
        let failed = |source| EngineError::Model {
            model: model.info().name.clone(),
            source,
        };
        let mut output = Answer {
            displacements: &mut displacements,
            forces: &mut scratch.point_forces,
        };
        model
            .predict(
                &scratch.points,
                target,
                &mut scratch.workspace,
                &mut output,
                &mut stages,
            )
            .map_err(failed)?;
        held::impose_held_displacements(
            &scratch.points,
            target.nodes,
            &mut displacements,
            &mut scratch.held_by_node,
        );
        let grasp_forces = match model.info().forces {
            Forces::Unavailable => None,
            _ => Some(grasp_totals(&scratch.points, &scratch.point_forces).map_err(failed)?),
        };
        let timing = Timing {
            resolve_us: (resolved - start).as_secs_f32() * 1e6,
            queue_us: (computing - resolved).as_secs_f32() * 1e6,
            prior_us: stages.prior_us,
            network_us: stages.network_us,
            total_us: start.elapsed().as_secs_f32() * 1e6,
            gpu: stages.gpu,
        };
        Ok(Prediction {
            model: model.info().name.clone(),
            displacements,
            node_ids: target.nodes.map(<[u32]>::to_vec),
            interaction_points: scratch.points.len(),
            grasp_forces,
            timing,
        })
    }

    fn take_scratch(&self) -> Scratch {
        self.scratch
            .lock()
            .map(|mut pool| pool.pop().unwrap_or_default())
            .unwrap_or_default()
    }

    fn return_scratch(&self, scratch: Scratch) {
        if let Ok(mut pool) = self.scratch.lock() {
            pool.push(scratch);
        }
    }
}

/// The force on each grasp: the sum of the forces on its interaction points.
pub fn grasp_totals(points: &InteractionPoints, point_forces: &[[f64; 3]]) -> Result<Vec<[f64; 3]>, ModelError> {
    if point_forces.len() != points.len() {
        return Err(ModelError::Runtime(format!(
            "gave {} point forces for {} interaction points",
            point_forces.len(),
            points.len()
        )));
    }
    Ok(points
        .grasp_ranges()
        .map(|range| {
            point_forces[range]
                .iter()
                .fold([0.0; 3], |sum, f| std::array::from_fn(|k| sum[k] + f[k]))
        })
        .collect())
}
