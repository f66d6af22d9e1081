//! The prior a network is composed with, as its manifest names it: the Kelvinlet with the model's own
//! parameters, or an exact linear answer through Green's functions (green-linear's or green-tangent's,
//! shared with the server's model of that name).

use std::sync::Arc;

use crate::engine::{KelvinletModel, ModelError, Target};
use crate::fem::GreenFunctions;
use crate::prior::{GpuPhases, InteractionPoints, Kelvinlet, Workspace};

pub enum ModelPrior {
    Kelvinlet(Kelvinlet),
    Green(Arc<GreenFunctions>),
}

impl ModelPrior {
    /// Writes the prior's displacement at `target`'s nodes into `out`, row-major (n, 3), and for a
    /// prior with exact forces (Green's functions) the force on each interaction point into
    /// `forces`; returns the GPU's phases when it was evaluated there.
    pub fn field(
        &self,
        points: &InteractionPoints,
        target: Target<'_>,
        workspace: &mut Workspace,
        out: &mut [f32],
        forces: &mut Vec<[f64; 3]>,
    ) -> Result<Option<GpuPhases>, ModelError> {
        match self {
            ModelPrior::Kelvinlet(kelvinlet) => {
                Ok(kelvinlet.solve_and_evaluate(points, workspace, target.cloud, out)?)
            }
            ModelPrior::Green(green) => {
                forces.clear();
                green.solve(&points.nodes, &points.displacements, target.nodes, out, forces)?;
                Ok(None)
            }
        }
    }

    /// The Kelvinlet, for the GPU path that evaluates it with a reduced basis in one dispatch.
    pub fn kelvinlet(&self) -> Option<&Kelvinlet> {
        match self {
            ModelPrior::Kelvinlet(kelvinlet) => Some(kelvinlet),
            ModelPrior::Green(_) => None,
        }
    }

    /// The served model this prior is, by name.
    pub fn name(&self) -> &'static str {
        match self {
            ModelPrior::Kelvinlet(_) => KelvinletModel::NAME,
            ModelPrior::Green(green) => green.stiffness().model_name(),
        }
    }
}
