//! Finite elements: linear elasticity (and the exact real-time linear model built on it).

pub mod green;
pub mod linear;

pub use green::{GreenLinear, GreenLinearModel};
pub use linear::{DofMap, LinearSystem, solve_dirichlet};

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
    #[error("{path}: {message}")]
    Cache { path: String, message: String },
}
