//! The held nodes answer exactly what the request prescribes: a grasper moves each node it holds by the
//! grasp's displacement (the finite elements' boundary condition), whatever a model's field gives there.
//! Exact models (green-linear, green-tangent) already do; the Kelvinlet's λ lets several points miss by a
//! little; a network whose field is a sum of smooth modes cannot follow the sharp peak at a grasp and
//! misses its held nodes by about half their displacement (docs/design.md §7).

use crate::prior::InteractionPoints;

/// How every field nak serves answers the held nodes, as `nak eval` records it beside its scores: a
/// score without it predates this rule (2026-12-07), when held nodes gave whatever the model gave.
pub const HELD_NODES: &str = "prescribed";

/// Writes each interaction point's prescribed displacement into its node's row of `field` (row-major
/// [rows, 3]). `rows` names the node of each row, or is `None` when row i is node i. `by_node` is scratch
/// space, kept between requests so that none allocates.
pub fn impose_held_displacements(
    points: &InteractionPoints,
    rows: Option<&[u32]>,
    field: &mut [f32],
    by_node: &mut Vec<(u32, usize)>,
) {
    match rows {
        None => {
            for (&node, displacement) in points.nodes.iter().zip(&points.displacements) {
                write(field, node as usize, displacement);
            }
        }
        Some(rows) => {
            // A selection may list thousands of nodes (the surface) against a few dozen held ones.
            by_node.clear();
            by_node.extend(points.nodes.iter().enumerate().map(|(point, &node)| (node, point)));
            by_node.sort_unstable();
            for (row, node) in rows.iter().enumerate() {
                let found = by_node.binary_search_by_key(node, |&(held, _)| held).ok();
                if let Some(displacement) = found.and_then(|i| points.displacements.get(by_node[i].1)) {
                    write(field, row, displacement);
                }
            }
        }
    }
}

fn write(field: &mut [f32], row: usize, displacement: &[f64; 3]) {
    debug_assert!(
        3 * row + 3 <= field.len(),
        "row {row} outside a field of {} values",
        field.len()
    );
    if let Some(values) = field.get_mut(3 * row..3 * row + 3) {
        for (value, &u) in values.iter_mut().zip(displacement) {
            *value = u as f32;
        }
    }
}
