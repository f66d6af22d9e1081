//! Models the engine can evaluate, behind one trait: the Kelvinlet prior now, exact and neural models
//! later.

use std::collections::BTreeMap;

use std::sync::Arc;

use crate::mesh::TetMesh;
use crate::prior::gpu::{GpuError, GpuPrior};
use crate::prior::{InteractionPoints, Kelvinlet, NodeCloud, SolveError, Workspace};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelKind {
    Prior,
    Exact,
    Neural,
}

/// What `ListModels` says about a model.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelInfo {
    pub name: String,
    pub kind: ModelKind,
    /// Content hash of the mesh it serves.
    pub mesh: String,
    /// `linear` or `nonlinear` for models trained on one regime; empty for analytic priors.
    pub regime: String,
    pub metadata: BTreeMap<String, String>,
}

/// Microseconds spent in a model's stages.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTiming {
    pub prior_us: f32,
    pub network_us: f32,
}

#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error(transparent)]
    Solve(#[from] SolveError),
    #[error("{0}")]
    Runtime(String),
    /// The request is valid in general but not for this model (e.g. a node it has no data for).
    #[error("{0}")]
    Unsupported(String),
}

/// The nodes a prediction answers for: their positions, and their ids unless they are every node in
/// order.
#[derive(Clone, Copy)]
pub struct Target<'a> {
    pub cloud: &'a NodeCloud,
    pub nodes: Option<&'a [u32]>,
}

/// A deformation model over one mesh.
pub trait DeformationModel: Send + Sync {
    fn info(&self) -> &ModelInfo;

    /// Writes the displacement at every node of `target` (row-major (n, 3)) into `out`.
    fn predict(
        &self,
        points: &InteractionPoints,
        target: Target<'_>,
        workspace: &mut Workspace,
        out: &mut [f32],
        timing: &mut StageTiming,
    ) -> Result<(), ModelError>;

    /// Called when the engine's node clouds live on `gpu`; `clouds[c]` lists the nodes of resident
    /// cloud `c` (`None`: every node in order). A model with mesh-sized data of its own (a reduced
    /// basis) uploads it here, so that its whole field is evaluated in one dispatch.
    fn attach_gpu(&self, gpu: &Arc<GpuPrior>, clouds: &[Option<&[u32]>]) -> Result<(), GpuError> {
        let _ = (gpu, clouds);
        Ok(())
    }
}

/// The Kelvinlet prior as a served model, named `kelvinlet`.
pub struct KelvinletModel {
    info: ModelInfo,
    prior: Kelvinlet,
}

impl KelvinletModel {
    pub const NAME: &'static str = "kelvinlet";

    pub fn new(mesh: &TetMesh) -> Self {
        let p = mesh.config.prior;
        let metadata = BTreeMap::from([
            ("poisson_ratio".to_owned(), p.poisson_ratio.to_string()),
            ("epsilon_m".to_owned(), p.epsilon.to_string()),
            ("lambda".to_owned(), p.lambda.to_string()),
            (
                "description".to_owned(),
                "rescaled regularized Kelvinlet (DESIGN.md §3), closed-form multi-point solve".to_owned(),
            ),
        ]);
        Self {
            info: ModelInfo {
                name: Self::NAME.to_owned(),
                kind: ModelKind::Prior,
                mesh: mesh.content_hash.clone(),
                regime: String::new(),
                metadata,
            },
            prior: Kelvinlet::new(p),
        }
    }
}

impl DeformationModel for KelvinletModel {
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
        let start = std::time::Instant::now();
        self.prior.solve(points, workspace)?;
        self.prior.evaluate(&workspace.coefficients, target.cloud, out);
        timing.prior_us = start.elapsed().as_secs_f32() * 1e6;
        Ok(())
    }
}
