//! Grasp sampling from the paper's distributions, datasets of ground truth, and the DCM metric.

pub mod dataset;
pub mod dcm;
pub mod generate;
pub mod sampling;

pub use sampling::{GraspSampler, SamplingError};
