//! A network served through ONNX Runtime under the model contract (DESIGN.md §7).

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Mutex;
use std::time::Instant;

use ort::session::Session;
use ort::session::builder::GraphOptimizationLevel;
use ort::value::{Outlet, TensorRef, ValueType};

use super::ModelLoadError;
use super::manifest::{Manifest, Mode};
use crate::engine::{DeformationModel, ModelError, ModelInfo, ModelKind, StageTiming, Target};
use crate::mesh::TetMesh;
use crate::prior::{InteractionPoints, Kelvinlet, NodeCloud, Workspace};

pub const INPUT: &str = "features";
pub const OUTPUT: &str = "displacement";

/// Per-request buffers, pooled: the feature tensor and, for models that read it, the prior field.
struct Buffers {
    /// [N, C], row-major; positions are filled once, the rest per request.
    features: Vec<f32>,
    /// Nodes whose displacement/active channels the last request set, to clear them in O(K).
    dirty: Vec<u32>,
    /// [N, 3] prior over all nodes (models reading the prior only).
    prior: Vec<f32>,
    /// The network's share of the selected rows, for residual models that run beside the prior.
    network: Vec<f32>,
    workspace: Workspace,
}

pub struct OnnxModel {
    info: ModelInfo,
    mode: Mode,
    reads_prior: bool,
    channels: usize,
    node_count: usize,
    prior: Kelvinlet,
    all_nodes: NodeCloud,
    /// `Session::run` needs exclusive access; one request at a time per model.
    session: Mutex<Session>,
    /// Buffers with positions already written, to copy when the pool is empty.
    template: Vec<f32>,
    pool: Mutex<Vec<Buffers>>,
}

impl OnnxModel {
    /// Loads `dir/model.onnx` under `dir/manifest.toml`, validates both against `mesh`, warms up.
    pub fn load(dir: &Path, mesh: &TetMesh, ort_dylib: Option<&Path>) -> Result<Self, ModelLoadError> {
        let manifest_path = dir.join("manifest.toml");
        let text = std::fs::read_to_string(&manifest_path)
            .map_err(|e| ModelLoadError::new(&manifest_path.display().to_string(), e.to_string()))?;
        let onnx_path = dir.join("model.onnx");
        let onnx = std::fs::read(&onnx_path)
            .map_err(|e| ModelLoadError::new(&onnx_path.display().to_string(), e.to_string()))?;
        Self::from_parts(&dir.display().to_string(), &text, &onnx, mesh, ort_dylib)
    }

    /// Builds a model from a manifest's text and a graph's bytes; `origin` names them in errors
    /// (`origin/manifest.toml`, `origin/model.onnx`).
    pub fn from_parts(
        origin: &str,
        manifest_text: &str,
        onnx: &[u8],
        mesh: &TetMesh,
        ort_dylib: Option<&Path>,
    ) -> Result<Self, ModelLoadError> {
        let manifest = Manifest::parse(manifest_text, &format!("{origin}/manifest.toml"))?;
        manifest.check_against(mesh, origin)?;
        let onnx_path = format!("{origin}/model.onnx");
        let environment = super::runtime::environment(ort_dylib)?;
        let session = Session::builder(environment)
            .and_then(|b| {
                b.with_optimization_level(GraphOptimizationLevel::Level3)
                    .map_err(Into::into)
            })
            .and_then(|b| b.with_intra_threads(threads()).map_err(Into::into))
            .and_then(|b| b.with_intra_op_spinning(false).map_err(Into::into))
            .and_then(|mut b| b.commit_from_memory(onnx))
            .map_err(|e| ModelLoadError::new(&onnx_path, format!("ONNX Runtime cannot load it: {e}")))?;
        let n = mesh.node_count();
        check_signature(&session, manifest.channels(), n, &onnx_path)?;

        let channels = manifest.channels();
        let mut template = vec![0.0f32; n * channels];
        for (row, p) in template.chunks_exact_mut(channels).zip(&mesh.positions) {
            for k in 0..3 {
                row[k] = p[k] as f32;
            }
        }
        let mut metadata: BTreeMap<String, String> = BTreeMap::new();
        metadata.insert("mode".into(), format!("{:?}", manifest.model.mode).to_lowercase());
        metadata.insert("method".into(), format!("{:?}", manifest.model.method).to_lowercase());
        let prior = manifest.prior;
        metadata.insert("prior.poisson_ratio".into(), prior.poisson_ratio.to_string());
        metadata.insert("prior.epsilon_m".into(), prior.epsilon.to_string());
        metadata.insert("prior.lambda".into(), prior.lambda.to_string());
        metadata.insert("inputs".into(), format!("{:?}", manifest.model.inputs).to_lowercase());
        metadata.insert("description".into(), manifest.model.description.clone());
        for (section, values) in [("metrics", &manifest.metrics), ("provenance", &manifest.provenance)] {
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
            },
            mode: manifest.model.mode,
            reads_prior: manifest.reads_prior(),
            channels,
            node_count: n,
            prior: Kelvinlet::new(manifest.prior),
            all_nodes: NodeCloud::new(mesh.positions.iter().copied()),
            session: Mutex::new(session),
            template,
            pool: Mutex::new(Vec::new()),
        };
        model
            .warm_up()
            .map_err(|e| ModelLoadError::new(origin, format!("warm-up failed: {e}")))?;
        Ok(model)
    }

    /// One inference on the rest state (nothing grasped): allocates ONNX Runtime's arenas and checks
    /// the output shape before the first client waits on it.
    fn warm_up(&self) -> Result<(), ModelError> {
        let mut buffers = self.take_buffers();
        let result = self.run_network(&buffers.features, |_| Ok(()));
        buffers.dirty.clear();
        self.return_buffers(buffers);
        result
    }

    fn take_buffers(&self) -> Buffers {
        let pooled = self.pool.lock().ok().and_then(|mut pool| pool.pop());
        pooled.unwrap_or_else(|| Buffers {
            features: self.template.clone(),
            dirty: Vec::new(),
            prior: if self.reads_prior {
                vec![0.0; 3 * self.node_count]
            } else {
                Vec::new()
            },
            network: Vec::new(),
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
            buffers.features[n as usize * c + 3..n as usize * c + 7].fill(0.0);
        }
        buffers.dirty.clear();
        for (&n, u) in points.nodes.iter().zip(&points.displacements) {
            let row = &mut buffers.features[n as usize * c..(n as usize + 1) * c];
            row[3] = u[0] as f32;
            row[4] = u[1] as f32;
            row[5] = u[2] as f32;
            row[6] = 1.0;
            buffers.dirty.push(n);
        }
        if self.reads_prior {
            for (row, u) in buffers.features.chunks_exact_mut(c).zip(buffers.prior.chunks_exact(3)) {
                row[7..10].copy_from_slice(u);
            }
        }
    }

    /// Runs the session on `features` and hands the [N, 3] output to `consume`.
    fn run_network(
        &self,
        features: &[f32],
        consume: impl FnOnce(&[f32]) -> Result<(), ModelError>,
    ) -> Result<(), ModelError> {
        let input = TensorRef::from_array_view(([1usize, self.node_count, self.channels], features))
            .map_err(|e| ModelError::Runtime(format!("cannot wrap the features: {e}")))?;
        let mut session = self
            .session
            .lock()
            .map_err(|_| ModelError::Runtime("the session was poisoned by an earlier panic".into()))?;
        let outputs = session
            .run(ort::inputs![INPUT => input])
            .map_err(|e| ModelError::Runtime(e.to_string()))?;
        let (shape, values) = outputs[OUTPUT]
            .try_extract_tensor::<f32>()
            .map_err(|e| ModelError::Runtime(format!("output {OUTPUT}: {e}")))?;
        if shape[..] != [1, self.node_count as i64, 3] {
            return Err(ModelError::Runtime(format!(
                "output {OUTPUT} has shape {shape:?}, expected [1, {}, 3]",
                self.node_count
            )));
        }
        consume(values)
    }
}

fn threads() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// The graph must take `features` [B, N, C] and give `displacement` [B, N, 3], f32, with N and B either
/// fixed to the mesh's values (N, 1) or symbolic.
fn check_signature(session: &Session, channels: usize, n: usize, origin: &str) -> Result<(), ModelLoadError> {
    let describe = |outlets: &[Outlet]| {
        outlets
            .iter()
            .map(|o| format!("{} {:?}", o.name(), o.dtype().tensor_shape().map(|s| s.to_vec())))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let check = |outlets: &[Outlet], name: &str, last: usize, what: &str| {
        let [outlet] = outlets else {
            return Err(ModelLoadError::new(
                origin,
                format!("expected one {what} named {name:?}, found: {}", describe(outlets)),
            ));
        };
        if outlet.name() != name {
            return Err(ModelLoadError::new(
                origin,
                format!(
                    "the {what} is named {:?}; the model contract names it {name:?}",
                    outlet.name()
                ),
            ));
        }
        let ValueType::Tensor { ty, shape, .. } = outlet.dtype() else {
            return Err(ModelLoadError::new(origin, format!("{what} {name:?} is not a tensor")));
        };
        let fits = |dim: i64, want: usize| dim < 0 || dim == want as i64;
        let ok_shape = shape.len() == 3 && fits(shape[0], 1) && fits(shape[1], n) && shape[2] == last as i64;
        if *ty != ort::value::TensorElementType::Float32 || !ok_shape {
            return Err(ModelLoadError::new(
                origin,
                format!(
                    "{what} {name:?} is {ty:?} {:?}; expected Float32 [batch, {n} (or symbolic), {last}]",
                    shape.to_vec()
                ),
            ));
        }
        Ok(())
    };
    check(session.inputs(), INPUT, channels, "input")?;
    check(session.outputs(), OUTPUT, 3, "output")
}

impl DeformationModel for OnnxModel {
    fn info(&self) -> &ModelInfo {
        &self.info
    }

    fn predict(
        &self,
        points: &InteractionPoints,
        target: Target<'_>,
        workspace: &mut Workspace,
        out: &mut [f32],
        timing: &mut StageTiming,
    ) -> Result<(), ModelError> {
        let mut buffers = self.take_buffers();
        let result = self.predict_with(points, target, workspace, &mut buffers, out, timing);
        self.return_buffers(buffers);
        result
    }
}

impl OnnxModel {
    fn predict_with(
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
            self.prior.solve(points, &mut buffers.workspace)?;
            self.prior
                .evaluate(&buffers.workspace.coefficients, &self.all_nodes, &mut buffers.prior);
            timing.prior_us = start.elapsed().as_secs_f32() * 1e6;
        }
        self.fill_features(points, buffers);
        let gather = |network: &[f32], out: &mut [f32], add: bool| {
            let rows: Box<dyn Iterator<Item = usize>> = match target.nodes {
                None => Box::new(0..self.node_count),
                Some(nodes) => Box::new(nodes.iter().map(|&n| n as usize)),
            };
            for (dst, n) in out.chunks_exact_mut(3).zip(rows) {
                let src = &network[3 * n..3 * n + 3];
                for k in 0..3 {
                    dst[k] = if add { dst[k] + src[k] } else { src[k] };
                }
            }
        };
        let features = &buffers.features;
        let network = |out: &mut [f32], add: bool, network_us: &mut f32| {
            let start = Instant::now();
            let result = self.run_network(features, |values| {
                gather(values, out, add);
                Ok(())
            });
            *network_us = start.elapsed().as_secs_f32() * 1e6;
            result
        };
        match self.mode {
            Mode::Direct => network(out, false, &mut timing.network_us),
            Mode::Residual if self.reads_prior => {
                gather(&buffers.prior, out, false);
                network(out, true, &mut timing.network_us)
            }
            Mode::Residual => {
                // Prior and network are independent: run them side by side, then add.
                let mut network_out = std::mem::take(&mut buffers.network);
                network_out.resize(out.len(), 0.0);
                let mut network_us = 0.0;
                let mut prior_us = 0.0;
                let (prior, net) = rayon::join(
                    || {
                        let start = Instant::now();
                        let r = self.prior.solve(points, workspace).map(|()| {
                            self.prior.evaluate(&workspace.coefficients, target.cloud, out);
                        });
                        prior_us = start.elapsed().as_secs_f32() * 1e6;
                        r
                    },
                    || network(&mut network_out, false, &mut network_us),
                );
                for (o, r) in out.iter_mut().zip(&network_out) {
                    *o += r;
                }
                buffers.network = network_out;
                prior?;
                net?;
                timing.prior_us = prior_us;
                timing.network_us = network_us;
                Ok(())
            }
        }
    }
}
