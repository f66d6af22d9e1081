//! Finite elements: linear elasticity (and the exact real-time linear model built on it), and
//! hyperelasticity with gravity preload for nonlinear ground truth.

pub mod factor;
pub mod green;
pub mod hyperelastic;
pub mod linear;
pub mod nonlinear;
pub mod ordering;
pub mod preload;
pub mod supernodal;

pub use green::{GreenError, GreenFunctions, Stiffness};
pub use linear::{DofMap, LinearSystem, nodal_forces, solve_dirichlet};

use std::path::{Path, PathBuf};

use crate::mesh::{Material, TetMesh};

/// Where a cache file is written before it is renamed into place: beside it, under a name of this
/// writer's own, so that processes sharing a cache (dataset shards on one volume) never write into
/// each other's half-written file; whichever renames last wins, with the same content.
fn cache_temporary(path: &Path) -> PathBuf {
    path.with_extension(format!("partial-{:016x}", rand::random::<u64>()))
}

/// Each region's material from model.toml, in region order.
pub fn region_materials(mesh: &TetMesh) -> Result<Vec<&Material>, FemError> {
    mesh.regions
        .iter()
        .map(|region| {
            mesh.config
                .materials
                .get(&region.name)
                .ok_or_else(|| FemError::Material(region.name.clone()))
        })
        .collect()
}

#[derive(Debug, thiserror::Error)]
pub enum FemError {
    #[error("region {0:?} has no material in model.toml")]
    Material(String),
    #[error("tetrahedron {0} is degenerate")]
    Degenerate(usize),
    #[error("assembly failed: {0}")]
    Assembly(String),
    #[error("the stiffness matrix is not positive definite ({0}): is any node fixed?")]
    NotPositiveDefinite(String),
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "no equilibrium at load step {step} (load fraction {load:.4}): {reason}; residual history (N) [{}]",
        scientific(.residuals)
    )]
    NotConverged {
        step: usize,
        load: f64,
        reason: String,
        residuals: Vec<f64>,
    },
    #[error("{path}: {message}")]
    Cache { path: String, message: String },
}

fn scientific(values: &[f64]) -> String {
    values.iter().map(|v| format!("{v:.2e}")).collect::<Vec<_>>().join(", ")
}
