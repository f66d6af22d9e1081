//! Requests for a load test, drawn from the paper's distribution p over the mesh the server reports.

use crate::client::Client;
use crate::data::{GraspSampler, SamplingError};
use crate::mesh::{GraspRegion, Sampling};
use crate::proto::v1::{self as pb, GetMeshRequest};
use crate::wire::{grasp_message, vec3_rows};

#[derive(Debug, thiserror::Error)]
pub enum RequestsError {
    #[error("GetMesh failed: {0}")]
    GetMesh(#[from] tonic::Status),
    #[error("the server's mesh does not describe its grasp distribution (Mesh.sampling is empty)")]
    NoSampling,
    #[error("the server's mesh is malformed: {0}")]
    Malformed(String),
    #[error(transparent)]
    Sampling(#[from] SamplingError),
}

/// A sampler for the mesh the server at the other end of `client` serves.
pub async fn sampler_for(client: &mut Client) -> Result<GraspSampler, RequestsError> {
    let mesh = client.get_mesh(GetMeshRequest::default()).await?.into_inner();
    let positions: Vec<[f64; 3]> = vec3_rows(&mesh.positions).map(|p| p.map(f64::from)).collect();
    if positions.len() != mesh.node_count as usize {
        return Err(RequestsError::Malformed(format!(
            "{} positions for {} nodes",
            positions.len(),
            mesh.node_count
        )));
    }
    let s = mesh.sampling.ok_or(RequestsError::NoSampling)?;
    let vec3 = |v: &[f64]| -> Result<[f64; 3], RequestsError> {
        v.try_into()
            .map_err(|_| RequestsError::Malformed("displacement bounds are not 3-vectors".into()))
    };
    let sampling = Sampling {
        displacement_min: vec3(&s.displacement_min_m)?,
        displacement_max: vec3(&s.displacement_max_m)?,
        neighbours: (s.neighbours_min as usize, s.neighbours_max as usize),
        grasp_regions: s
            .grasp_regions
            .iter()
            .map(|r| GraspRegion {
                node_set: r.node_set.clone(),
                weight: r.weight,
            })
            .collect(),
    };
    let sets = mesh.node_sets;
    Ok(GraspSampler::new(&positions, &mesh.surface_nodes, &sampling, |name| {
        sets.iter().find(|s| s.name == name).map(|s| s.nodes.clone())
    })?)
}

/// `count` requests for `model`, samples `0..count` of the stream `seed`.
pub fn draw(
    sampler: &GraspSampler,
    model: &str,
    graspers: usize,
    seed: u64,
    count: usize,
) -> Result<Vec<pb::PredictRequest>, RequestsError> {
    (0..count as u64)
        .map(|i| {
            let grasps = sampler
                .sample(seed, i, graspers)?
                .iter()
                .map(|(_, g)| grasp_message(g))
                .collect();
            Ok(pb::PredictRequest {
                model: model.to_owned(),
                grasps,
                sequence: i,
                ..Default::default()
            })
        })
        .collect()
}
