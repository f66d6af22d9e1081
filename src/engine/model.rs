//! Models the engine can evaluate, behind one trait: the Kelvinlet prior now, exact and neural models
//! later.

use std::collections::BTreeMap;

use std::sync::Arc;

use crate::mesh::TetMesh;
use crate::prior::gpu::{GpuError, GpuPrior};
use crate::prior::{Coefficients, GpuPhases, InteractionPoints, Kelvinlet, NodeCloud, SolveError, Workspace};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelKind {
    Prior,
    Exact,
    Neural,
}

/// Whether, and how well, a model knows the force at each grasper.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Forces {
    /// Answers carry no forces.
    #[default]
    Unavailable,
    /// The forces of the model's own discretization (green-linear: K·u at the held nodes).
    Exact,
    /// A closed-form estimate (the Kelvinlet's point loads).
    Estimate,
    /// A network's `forces` output, trained on the finite elements' forces.
    Learned,
}

/// The metadata key naming the hyperelastic law a nonlinear model's answers were made under
/// (`ln-j-squared`, …): a trained network's data, or green-tangent's own preload.
pub const VOLUMETRIC_LAW_KEY: &str = "volumetric_law";

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
    pub forces: Forces,
}

/// Microseconds spent in a model's stages.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTiming {
    pub prior_us: f32,
    pub network_us: f32,
    /// Where the prior's time went, when its field was evaluated on the GPU.
    pub gpu: Option<GpuPhases>,
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

/// Where a model writes its answer.
pub struct Answer<'a> {
    /// Row-major (n, 3) displacements of the target's nodes.
    pub displacements: &'a mut [f32],
    /// The force on each interaction point, for models that give forces.
    pub forces: &'a mut Vec<[f64; 3]>,
}

/// A deformation model over one mesh.
pub trait DeformationModel: Send + Sync {
    fn info(&self) -> &ModelInfo;

    /// Writes the displacement at every node of `target` (row-major (n, 3)) into `out`, and, when
    /// the model's info promises forces, the force (N) on each interaction point into `forces`
    /// (cleared by the caller; left empty otherwise).
    fn predict(
        &self,
        points: &InteractionPoints,
        target: Target<'_>,
        workspace: &mut Workspace,
        out: &mut Answer<'_>,
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
    /// Per node, the stiffness `16πμ(1−ν)` that turns a solved coefficient `s·k` into its point
    /// load; `None` when the mesh's regions have no materials (the model then gives no forces).
    load_per_coefficient: Option<Vec<f64>>,
}

impl KelvinletModel {
    pub const NAME: &'static str = "kelvinlet";

    pub fn new(mesh: &TetMesh) -> Self {
        let p = mesh.config.prior;
        let load_per_coefficient = nodal_shear_moduli(mesh).map(|mu| {
            mu.into_iter()
                .map(|mu| 16.0 * std::f64::consts::PI * mu * (1.0 - p.poisson_ratio))
                .collect()
        });
        let mut metadata = BTreeMap::from([
            ("poisson_ratio".to_owned(), p.poisson_ratio.to_string()),
            ("epsilon_m".to_owned(), p.epsilon.to_string()),
            ("lambda".to_owned(), p.lambda.to_string()),
            (
                "description".to_owned(),
                "rescaled regularized Kelvinlet (docs/design.md §3), closed-form multi-point solve".to_owned(),
            ),
        ]);
        let forces = match &load_per_coefficient {
            Some(_) => {
                metadata.insert("forces".to_owned(), FORCE_ESTIMATE.to_owned());
                Forces::Estimate
            }
            None => {
                metadata.insert(
                    "forces".to_owned(),
                    "none: the mesh's regions have no materials".to_owned(),
                );
                Forces::Unavailable
            }
        };
        Self {
            info: ModelInfo {
                name: Self::NAME.to_owned(),
                kind: ModelKind::Prior,
                mesh: mesh.content_hash.clone(),
                regime: String::new(),
                metadata,
                forces,
            },
            prior: Kelvinlet::new(p),
            load_per_coefficient,
        }
    }

    /// The point load of each solved Kelvinlet: de Goes and James's regularized Kelvinlet for a load
    /// `f` is `u = [(a−b)/r_ε I + b/r_ε³ r rᵀ + (a/2) ε²/r_ε³ I] f` with `a = 1/(4πμ)`, `b = a/(4(1−ν))`,
    /// which is `1/(16πμ(1−ν))` times docs/design.md §3's bracket; the served field is that bracket times the
    /// coefficient `s·k`, so `f = 16πμ(1−ν) · s·k`, with μ at the held node.
    pub fn point_loads(&self, points: &InteractionPoints, coefficients: &Coefficients, forces: &mut Vec<[f64; 3]>) {
        let Some(stiffness) = &self.load_per_coefficient else {
            return;
        };
        let c = coefficients;
        forces.extend(points.nodes.iter().enumerate().map(|(j, &node)| {
            let s = stiffness[node as usize];
            [s * c.kx[j] as f64, s * c.ky[j] as f64, s * c.kz[j] as f64]
        }));
    }
}

/// What ListModels says about the Kelvinlet's forces.
const FORCE_ESTIMATE: &str = "estimate: the regularized Kelvinlets' point loads in an infinite medium \
                              with the held node's shear modulus (docs/api.md: Reaction forces)";

/// Each node's shear modulus (Pa): the volume-weighted mean over its tetrahedra (the region's own
/// inside a region). `None` when a region has no material.
fn nodal_shear_moduli(mesh: &TetMesh) -> Option<Vec<f64>> {
    let materials = crate::fem::region_materials(mesh).ok()?;
    let mut weighted = vec![0.0; mesh.node_count()];
    let mut volume = vec![0.0; mesh.node_count()];
    for ((tet, &region), &v) in mesh.tets.iter().zip(&mesh.tet_region).zip(&mesh.tet_volumes) {
        for &n in tet {
            weighted[n as usize] += v * materials[region as usize].shear_modulus;
            volume[n as usize] += v;
        }
    }
    Some(
        weighted
            .iter()
            .zip(&volume)
            .map(|(w, v)| if *v > 0.0 { w / v } else { 0.0 })
            .collect(),
    )
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
        out: &mut Answer<'_>,
        timing: &mut StageTiming,
    ) -> Result<(), ModelError> {
        let start = std::time::Instant::now();
        timing.gpu = self
            .prior
            .solve_and_evaluate(points, workspace, target.cloud, out.displacements)?;
        self.point_loads(points, &workspace.coefficients, out.forces);
        timing.prior_us = start.elapsed().as_secs_f32() * 1e6;
        Ok(())
    }
}
