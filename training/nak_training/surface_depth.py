"""How much organ lies beneath each surface node: the distance along its inward normal to where that ray
leaves the organ again, as nak computes it (src/mesh/depth.rs: the same rays, triangles and tolerances;
tests check nak serves a graph reading it as ONNX Runtime computes it from these values)."""

from __future__ import annotations

import numpy as np

# A ray through a shared edge or vertex of the far surface hits either triangle.
EDGE_SLACK = 1e-9
# A triangle this close to parallel to the ray (|det| against |e1| |e2|) is not hit.
PARALLEL = 1e-12


def boundary_triangles(tets: np.ndarray) -> np.ndarray:
    """The faces of exactly one tetrahedron [F, 3] (orientation is not needed here)."""
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    _, first, counts = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True)
    return faces[first[counts == 1]]


def inward_depths(
    positions: np.ndarray, tets: np.ndarray, normals: np.ndarray, surface_nodes: np.ndarray
) -> np.ndarray:
    """Per node, f64 [N] (zero off the surface, and where the ray leaves through no triangle): the
    distance (m) from the node along its inward normal to the nearest boundary triangle not touching it
    (Möller–Trumbore over every triangle, node by node)."""
    triangles = boundary_triangles(tets)
    a, b, c = (positions[triangles[:, i]] for i in range(3))
    e1, e2 = b - a, c - a
    lengths = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
    depths = np.zeros(len(positions))
    for node in surface_nodes:
        direction = -normals[node]
        p = np.cross(direction, e2)
        det = np.einsum("ij,ij->i", e1, p)
        s = positions[node] - a
        q = np.cross(s, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.einsum("ij,ij->i", s, p) / det
            v = q @ direction / det
            t = np.einsum("ij,ij->i", e2, q) / det
        hit = (np.abs(det) > PARALLEL * lengths) & (u >= -EDGE_SLACK) & (v >= -EDGE_SLACK)
        hit &= (u + v <= 1.0 + EDGE_SLACK) & (t > 0.0) & ~(triangles == node).any(axis=1)
        depths[node] = t[hit].min() if hit.any() else 0.0
    return depths
