//! Between the wire (`nak.v1`) and the engine.

use bytes::Bytes;
use tonic::{Code, Status};

use crate::engine::{EngineError, Forces, Grasp, ModelError, ModelInfo, ModelKind, Prediction, Request, Selection};
use crate::mesh::{Sampling, TetMesh};
use crate::proto::v1 as pb;

/// A vector of f32 handed to the response as little-endian bytes without copying.
struct F32Bytes(Vec<f32>);

impl AsRef<[u8]> for F32Bytes {
    fn as_ref(&self) -> &[u8] {
        bytemuck::cast_slice(&self.0)
    }
}

// The wire format is little-endian; on such hosts an f32 slice already is those bytes.
const _: () = assert!(
    cfg!(target_endian = "little"),
    "nak's zero-copy responses assume a little-endian host"
);

pub fn f32_bytes(values: Vec<f32>) -> Bytes {
    Bytes::from_owner(F32Bytes(values))
}

/// The (x, y, z) rows of packed little-endian f32 bytes, as `Mesh.positions` and
/// `PredictResponse.displacements` carry them.
pub fn vec3_rows(bytes: &[u8]) -> impl Iterator<Item = [f32; 3]> + '_ {
    bytes
        .chunks_exact(12)
        .map(|c| std::array::from_fn(|k| f32::from_le_bytes([c[4 * k], c[4 * k + 1], c[4 * k + 2], c[4 * k + 3]])))
}

/// (node id, displacement) of every row of an answer: its `node_ids` when present, else 0, 1, 2, ….
pub fn response_rows(response: &pb::PredictResponse) -> impl Iterator<Item = (u32, [f32; 3])> + '_ {
    let ids: Box<dyn Iterator<Item = u32> + '_> = if response.node_ids.is_empty() {
        Box::new(0u32..)
    } else {
        Box::new(response.node_ids.iter().copied())
    };
    ids.zip(vec3_rows(&response.displacements))
}

fn vec3(v: Option<&pb::Vec3>) -> Option<[f64; 3]> {
    v.map(|v| [v.x as f64, v.y as f64, v.z as f64])
}

/// The wire form of a grasp (what clients such as `nak bench` send).
pub fn grasp_message(g: &Grasp) -> pb::Grasp {
    let v = |v: [f64; 3]| pb::Vec3 {
        x: v[0] as f32,
        y: v[1] as f32,
        z: v[2] as f32,
    };
    pb::Grasp {
        nodes: g.nodes.clone(),
        point: g.point.map(v),
        radius: g.radius as f32,
        displacement: Some(v(g.displacement)),
    }
}

pub fn request(message: &pb::PredictRequest) -> Result<Request, Status> {
    let selection = match pb::NodeSelection::try_from(message.selection) {
        Ok(pb::NodeSelection::All) => Selection::All,
        Ok(pb::NodeSelection::Surface) => Selection::Surface,
        Ok(pb::NodeSelection::List) => Selection::List(message.nodes.clone()),
        Err(_) => {
            return Err(Status::invalid_argument(format!(
                "unknown node selection {}",
                message.selection
            )));
        }
    };
    let grasps = message
        .grasps
        .iter()
        .map(|g| Grasp {
            nodes: g.nodes.clone(),
            point: vec3(g.point.as_ref()),
            radius: g.radius as f64,
            // An absent displacement is the zero vector, as proto3 would default it.
            displacement: vec3(g.displacement.as_ref()).unwrap_or([0.0; 3]),
        })
        .collect();
    Ok(Request {
        model: message.model.clone(),
        mesh: message.mesh.clone(),
        grasps,
        selection,
    })
}

pub fn response(sequence: u64, prediction: Prediction) -> pb::PredictResponse {
    let node_count = (prediction.displacements.len() / 3) as u32;
    let t = prediction.timing;
    pb::PredictResponse {
        sequence,
        node_count,
        displacements: f32_bytes(prediction.displacements),
        node_ids: prediction.node_ids.unwrap_or_default(),
        timing: Some(pb::Timing {
            resolve_us: t.resolve_us,
            prior_us: t.prior_us,
            network_us: t.network_us,
            total_us: t.total_us,
            queue_us: t.queue_us,
            gpu: t.gpu.map(|g| pb::GpuTiming {
                queue_us: g.queue_us,
                upload_us: g.upload_us,
                dispatch_us: g.dispatch_us,
                wait_us: g.wait_us,
                copy_us: g.copy_us,
                batch: g.batch,
            }),
        }),
        model: prediction.model,
        interaction_points: prediction.interaction_points as u32,
        error: None,
        grasp_forces: prediction
            .grasp_forces
            .unwrap_or_default()
            .into_iter()
            .map(|f| pb::Vec3 {
                x: f[0] as f32,
                y: f[1] as f32,
                z: f[2] as f32,
            })
            .collect(),
    }
}

pub fn status(error: &EngineError) -> Status {
    let code = match error {
        EngineError::NotFound(_) => Code::NotFound,
        EngineError::InvalidArgument(_) => Code::InvalidArgument,
        EngineError::Model {
            source: ModelError::Unsupported(_),
            ..
        } => Code::InvalidArgument,
        EngineError::Model { .. } => Code::Internal,
    };
    Status::new(code, error.to_string())
}

pub fn model_info(info: &ModelInfo) -> pb::ModelInfo {
    pb::ModelInfo {
        name: info.name.clone(),
        kind: match info.kind {
            ModelKind::Prior => pb::ModelKind::Prior,
            ModelKind::Exact => pb::ModelKind::Exact,
            ModelKind::Neural => pb::ModelKind::Neural,
        } as i32,
        mesh: info.mesh.clone(),
        regime: info.regime.clone(),
        metadata: info.metadata.clone().into_iter().collect(),
        forces: match info.forces {
            Forces::Unavailable => pb::Forces::Unavailable,
            Forces::Exact => pb::Forces::Exact,
            Forces::Estimate => pb::Forces::Estimate,
            Forces::Learned => pb::Forces::Learned,
        } as i32,
    }
}

pub fn mesh(mesh: &TetMesh) -> pb::Mesh {
    let positions: Vec<f32> = mesh.positions.iter().flatten().map(|&v| v as f32).collect();
    let triangles: Vec<u32> = mesh.surface.iter().flatten().copied().collect();
    let p = mesh.config.prior;
    pb::Mesh {
        name: mesh.config.name.clone(),
        content_hash: mesh.content_hash.clone(),
        node_count: mesh.node_count() as u32,
        positions: f32_bytes(positions),
        surface_triangles: Bytes::copy_from_slice(bytemuck::cast_slice(&triangles)),
        node_sets: mesh
            .node_sets
            .iter()
            .map(|(name, nodes)| pb::NodeSet {
                name: name.clone(),
                nodes: nodes.clone(),
            })
            .collect(),
        regions: mesh
            .regions
            .iter()
            .map(|r| pb::Region {
                name: r.name.clone(),
                id: r.id,
                volume_m3: r.volume,
            })
            .collect(),
        surface_nodes: mesh.surface_nodes.clone(),
        prior: Some(pb::KelvinletParameters {
            poisson_ratio: p.poisson_ratio,
            epsilon_m: p.epsilon,
            lambda: p.lambda,
        }),
        sampling: Some(sampling(&mesh.config.sampling)),
    }
}

fn sampling(s: &Sampling) -> pb::SamplingParameters {
    pb::SamplingParameters {
        displacement_min_m: s.displacement_min.to_vec(),
        displacement_max_m: s.displacement_max.to_vec(),
        neighbours_min: s.neighbours.0 as u32,
        neighbours_max: s.neighbours.1 as u32,
        grasp_regions: s
            .grasp_regions
            .iter()
            .map(|r| pb::GraspRegion {
                node_set: r.node_set.clone(),
                weight: r.weight,
            })
            .collect(),
    }
}
