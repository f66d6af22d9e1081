//! The exact linear models `green-linear` and `green-tangent` as served models: Green's functions
//! (`fem::green`) behind the engine's model trait.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Instant;

use crate::engine::{
    Answer, DeformationModel, Forces, ModelError, ModelInfo, ModelKind, Regime, StageTiming, Target, VOLUMETRIC_LAW_KEY,
};
use crate::fem::{GreenError, GreenFunctions, Stiffness};
use crate::mesh::TetMesh;
use crate::prior::{InteractionPoints, Workspace};

/// Green's functions as a served model: `green-linear` or `green-tangent`.
pub struct GreenModel {
    info: ModelInfo,
    green: Arc<GreenFunctions>,
}

impl GreenModel {
    pub const LINEAR: &'static str = Stiffness::Linear.model_name();
    pub const TANGENT: &'static str = Stiffness::PreloadTangent.model_name();

    pub fn new(mesh: &TetMesh, green: Arc<GreenFunctions>) -> Self {
        let stiffness = green.stiffness();
        let (description, regime, forces, forces_text) = match stiffness {
            Stiffness::Linear => (
                "exact linear FEM through precomputed Green's functions (capacitance matrix)",
                Regime::Linear,
                Forces::Exact,
                "exact: (G[S,S])⁻¹ u_S, the linear FEM's K·u at the held nodes",
            ),
            Stiffness::PreloadTangent => (
                "the hyperelastic model linearized about its gravity-preloaded equilibrium, through \
                 precomputed Green's functions (capacitance matrix)",
                Regime::Nonlinear,
                Forces::Estimate,
                "(G[S,S])⁻¹ u_S, the tangent's K·u at the held nodes: the change of the held nodes' \
                 force from the preloaded state, exact for small grasps",
            ),
        };
        let mut metadata = BTreeMap::from([
            ("description".to_owned(), description.to_owned()),
            ("candidate_nodes".to_owned(), green.candidates().len().to_string()),
            ("forces".to_owned(), forces_text.to_owned()),
            ("cache".to_owned(), green.path.display().to_string()),
        ]);
        if stiffness == Stiffness::PreloadTangent {
            metadata.insert(VOLUMETRIC_LAW_KEY.into(), mesh.config.volumetric_law.name().into());
        }
        Self {
            info: ModelInfo {
                name: stiffness.model_name().to_owned(),
                kind: ModelKind::Exact,
                mesh: mesh.content_hash.clone(),
                regime: regime.name().to_owned(),
                metadata,
                forces,
            },
            green,
        }
    }
}

impl DeformationModel for GreenModel {
    fn info(&self) -> &ModelInfo {
        &self.info
    }

    fn predict(
        &self,
        points: &InteractionPoints,
        target: Target<'_>,
        _workspace: &mut Workspace,
        out: &mut Answer<'_>,
        timing: &mut StageTiming,
    ) -> Result<(), ModelError> {
        let start = Instant::now();
        self.green.solve(
            &points.nodes,
            &points.displacements,
            target.nodes,
            out.displacements,
            out.forces,
        )?;
        timing.network_us = start.elapsed().as_secs_f32() * 1e6;
        Ok(())
    }
}

impl From<GreenError> for ModelError {
    fn from(e: GreenError) -> Self {
        match e {
            // A grasp away from the regions the columns were computed for: valid, but not here.
            GreenError::NoColumn { .. } => ModelError::Unsupported(e.to_string()),
            GreenError::NotPositiveDefinite => ModelError::Runtime(e.to_string()),
        }
    }
}
