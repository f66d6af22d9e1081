//! Grasp sampling from the paper's distributions, datasets of ground truth, the DCM metric and the
//! error of grasp forces.

pub mod dataset;
pub mod dcm;
pub mod force_error;
pub mod generate;
pub mod join;
pub mod sampling;
pub mod shard;

pub use sampling::{GraspSampler, SamplingError};
