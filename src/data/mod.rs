//! Sampling grasps from the paper's distributions (and, later, datasets and DCM).

pub mod sampling;

pub use sampling::{GraspSampler, SamplingError};
