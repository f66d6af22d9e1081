//! Turning a request's grasps into interaction points, refusing anything malformed with a message that
//! says which grasp and which value.

use super::{EngineError, Limits};
use crate::mesh::TetMesh;
use crate::prior::InteractionPoints;

/// One grasper as a client describes it.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Grasp {
    /// Surface nodes held; empty when the grasp is given by `point`.
    pub nodes: Vec<u32>,
    /// Hold the surface nodes within `radius` of this point (the nearest one when `radius` is 0).
    pub point: Option<[f64; 3]>,
    pub radius: f64,
    /// How far every held node moves (metres).
    pub displacement: [f64; 3],
}

/// Resolves `grasps` into `out` (cleared first), grasp by grasp. Each held node is one interaction
/// point; a node held by two grasps must be moved the same way by both and is then counted once, for
/// the first.
pub fn resolve(
    mesh: &TetMesh,
    limits: &Limits,
    grasps: &[Grasp],
    out: &mut InteractionPoints,
) -> Result<(), EngineError> {
    out.clear();
    if grasps.is_empty() {
        return Err(EngineError::invalid("the request has no grasps: give at least one"));
    }
    for (g, grasp) in grasps.iter().enumerate() {
        let u = grasp.displacement;
        if u.iter().any(|v| !v.is_finite()) {
            return Err(EngineError::invalid(format!(
                "grasps[{g}].displacement is not finite: {u:?}"
            )));
        }
        let magnitude = u.iter().map(|v| v * v).sum::<f64>().sqrt();
        if magnitude > limits.max_displacement_m {
            return Err(EngineError::invalid(format!(
                "grasps[{g}].displacement is {:.1} mm, above the server's bound of {:.1} mm",
                magnitude * 1e3,
                limits.max_displacement_m * 1e3
            )));
        }
        match (grasp.nodes.is_empty(), grasp.point) {
            (false, Some(_)) => {
                return Err(EngineError::invalid(format!(
                    "grasps[{g}] gives both nodes and a point: give one of them"
                )));
            }
            (true, None) => {
                return Err(EngineError::invalid(format!(
                    "grasps[{g}] holds nothing: give nodes or a point"
                )));
            }
            (false, None) => {
                for &node in &grasp.nodes {
                    check_node(mesh, g, node)?;
                    add(out, limits, mesh, g, node, u)?;
                }
            }
            (true, Some(point)) => {
                if point.iter().any(|v| !v.is_finite()) || !grasp.radius.is_finite() || grasp.radius < 0.0 {
                    return Err(EngineError::invalid(format!(
                        "grasps[{g}] has a point {point:?} or radius {} that is not a finite, non-negative \
                         distance",
                        grasp.radius
                    )));
                }
                snap(mesh, limits, g, point, grasp.radius, u, out)?;
            }
        }
        out.end_grasp();
    }
    Ok(())
}

fn check_node(mesh: &TetMesh, g: usize, node: u32) -> Result<(), EngineError> {
    let n = mesh.node_count();
    if node as usize >= n {
        return Err(EngineError::invalid(format!(
            "grasps[{g}] holds node {node}, but the mesh has {n} nodes (0..{})",
            n - 1
        )));
    }
    if !mesh.is_surface[node as usize] {
        return Err(EngineError::invalid(format!(
            "grasps[{g}] holds node {node}, which is inside the organ: graspers hold surface nodes \
             (GetMesh lists them)"
        )));
    }
    if mesh.is_fixed(node) {
        return Err(EngineError::invalid(format!(
            "grasps[{g}] holds node {node}, which is in the mesh's `fixed` set: the fixture holds it in \
             place, so no grasper can move it"
        )));
    }
    Ok(())
}

/// Free surface nodes within `radius` of `point`, or the nearest one when `radius` is 0; fixed nodes
/// are skipped (the fixture holds them).
fn snap(
    mesh: &TetMesh,
    limits: &Limits,
    g: usize,
    point: [f64; 3],
    radius: f64,
    u: [f64; 3],
    out: &mut InteractionPoints,
) -> Result<(), EngineError> {
    let distance_sq = |n: u32| {
        let p = mesh.positions[n as usize];
        (0..3).map(|k| (p[k] - point[k]).powi(2)).sum::<f64>()
    };
    let free = || mesh.surface_nodes.iter().copied().filter(|&n| !mesh.is_fixed(n));
    if radius == 0.0 {
        let nearest = free().min_by(|&a, &b| distance_sq(a).total_cmp(&distance_sq(b)));
        return match nearest {
            Some(node) => add(out, limits, mesh, g, node, u),
            None => Err(EngineError::invalid("the mesh has no free surface nodes")),
        };
    }
    let before = out.len();
    for node in free() {
        if distance_sq(node) <= radius * radius {
            add(out, limits, mesh, g, node, u)?;
        }
    }
    if out.len() == before && !out.nodes.iter().any(|&n| distance_sq(n) <= radius * radius) {
        return Err(EngineError::invalid(format!(
            "grasps[{g}] holds no node: no free surface node lies within {:.1} mm of {point:?} (nodes of \
             the `fixed` set are held by the fixture)",
            radius * 1e3
        )));
    }
    Ok(())
}

fn add(
    out: &mut InteractionPoints,
    limits: &Limits,
    mesh: &TetMesh,
    g: usize,
    node: u32,
    u: [f64; 3],
) -> Result<(), EngineError> {
    // K is small (at most a few hundred), so a linear scan beats a hash set.
    if let Some(i) = out.nodes.iter().position(|&n| n == node) {
        if out.displacements[i] != u {
            return Err(EngineError::invalid(format!(
                "node {node} is held by two grasps with different displacements ({:?} and grasps[{g}]: {u:?})",
                out.displacements[i]
            )));
        }
        return Ok(());
    }
    if out.len() >= limits.max_interaction_points {
        return Err(EngineError::invalid(format!(
            "the grasps hold more than {} nodes, the server's limit on interaction points",
            limits.max_interaction_points
        )));
    }
    out.push(node, mesh.positions[node as usize], u);
    Ok(())
}
