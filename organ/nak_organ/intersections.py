"""Self-intersection of a triangle surface: pairs of faces that meet other than where the mesh joins them.

Candidate pairs come from a grid of the faces' boxes (grid.py). Two triangles meet if an edge of one
meets the other (when they are not coplanar, their intersection is a segment whose ends lie on edges;
when they are, an overlap contains an edge crossing or a vertex of one inside the other), so each pair
is decided by segment–triangle tests, by how many vertices the two share:

* none: the six edges of each against the other triangle; touching counts.
* one vertex v: faces that meet anywhere but v have a point beyond v on both, and the segment from v to
  the farther of the two reaches the edge opposite v: so each opposite edge against the other triangle.
* an edge: they meet beyond it only when folded flat onto each other (opposite vertices on the same side
  of the shared edge, in one plane).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import geometry, grid

Floats = NDArray[np.float64]
Ints = NDArray[np.int64]

# Folded faces: the far vertex of one lies this close to the other's plane, relative to its height.
FOLD_TOLERANCE = 1e-6


def intersecting_pairs(vertices: Floats, faces: Ints) -> Ints:
    """(K, 2) pairs of face indices, i < j, sorted, of faces that meet other than at shared vertices
    and edges."""
    corners = vertices[faces]
    i, j = grid.overlapping_boxes(corners.min(axis=1), corners.max(axis=1))
    fi, fj = faces[i], faces[j]
    same = fi[:, :, None] == fj[:, None, :]
    shared = same.sum(axis=(1, 2))
    meets = np.zeros(len(i), dtype=bool)
    for count, test in ((0, _disjoint_meet), (1, _vertex_sharing_meet), (2, _folded)):
        rows = np.flatnonzero(shared == count)
        if len(rows):
            meets[rows] = test(vertices, fi[rows], fj[rows], same[rows])
    return np.column_stack([i[meets], j[meets]])


def _disjoint_meet(vertices: Floats, fi: Ints, fj: Ints, same: NDArray[np.bool_]) -> NDArray[np.bool_]:
    a, b = vertices[fi], vertices[fj]
    meets = np.zeros(len(fi), dtype=bool)
    for first, second in ((a, b), (b, a)):
        for k in range(3):
            p, q = first[:, k], first[:, (k + 1) % 3]
            meets |= geometry.segments_meet_triangles(p, q, second[:, 0], second[:, 1], second[:, 2])
    return meets


def _vertex_sharing_meet(vertices: Floats, fi: Ints, fj: Ints, same: NDArray[np.bool_]) -> NDArray[np.bool_]:
    rows = np.arange(len(fi))
    # Positions of the shared vertex in each face; the edge opposite it joins the other two corners.
    at_i = np.argmax(same.any(axis=2), axis=1)
    at_j = np.argmax(same.any(axis=1), axis=1)
    a, b = vertices[fi], vertices[fj]
    meets = np.zeros(len(fi), dtype=bool)
    for first, second, at in ((a, b, at_i), (b, a, at_j)):
        p, q = first[rows, (at + 1) % 3], first[rows, (at + 2) % 3]
        meets |= geometry.segments_meet_triangles(p, q, second[:, 0], second[:, 1], second[:, 2])
    return meets


def _folded(vertices: Floats, fi: Ints, fj: Ints, same: NDArray[np.bool_]) -> NDArray[np.bool_]:
    rows = np.arange(len(fi))
    lone_i = np.argmin(same.any(axis=2), axis=1)
    lone_j = np.argmin(same.any(axis=1), axis=1)
    u, w = vertices[fi[rows, (lone_i + 1) % 3]], vertices[fi[rows, (lone_i + 2) % 3]]
    a, b = vertices[fi[rows, lone_i]], vertices[fj[rows, lone_j]]
    edge = w - u
    edge /= np.linalg.norm(edge, axis=1)[:, None]

    def across(x: Floats) -> Floats:
        """The part of x - u perpendicular to the shared edge."""
        r = x - u
        perpendicular: Floats = r - np.einsum("ij,ij->i", r, edge)[:, None] * edge
        return perpendicular

    ha, hb = across(a), across(b)
    normal = np.cross(edge, ha)
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    off_plane = np.abs(np.einsum("ij,ij->i", hb, normal))
    same_side = np.einsum("ij,ij->i", ha, hb) > 0
    folded: NDArray[np.bool_] = same_side & (off_plane <= FOLD_TOLERANCE * np.linalg.norm(hb, axis=1))
    return folded
