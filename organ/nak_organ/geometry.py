"""Vectorized triangle geometry: areas, closest points, segment–triangle intersection, nearest triangles.

Every function takes arrays of rows (one query per row) so that a surface of tens of thousands of
triangles is handled by numpy, not by a Python loop.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from . import grid

Floats = NDArray[np.float64]
Ints = NDArray[np.int64]
Bools = NDArray[np.bool_]


def face_normals(vertices: Floats, faces: Ints) -> Floats:
    """(F, 3) normals of length twice each triangle's area, by the right-hand rule."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return np.cross(b - a, c - a)


def face_areas(vertices: Floats, faces: Ints) -> Floats:
    areas: Floats = 0.5 * np.linalg.norm(face_normals(vertices, faces), axis=1)
    return areas


def enclosed_volume(vertices: Floats, faces: Ints) -> float:
    """Signed volume a closed surface encloses (divergence theorem): positive when it faces outwards."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return float(np.sum(np.einsum("ij,ij->i", a, np.cross(b, c))) / 6.0)


def _dot(u: Floats, v: Floats) -> Floats:
    """Row-wise dot products."""
    products: Floats = np.einsum("ij,ij->i", u, v)
    return products


def closest_points(p: Floats, a: Floats, b: Floats, c: Floats) -> tuple[Floats, Floats]:
    """Closest point of each triangle (a, b, c) to p, and its barycentric coordinates (Ericson,
    Real-Time Collision Detection §5.1.5: the Voronoi region of p decides vertex, edge or face)."""
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    d1, d2, d3, d4, d5, d6 = _dot(ab, ap), _dot(ac, ap), _dot(ab, bp), _dot(ac, bp), _dot(ab, cp), _dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        inside = 1.0 / (va + vb + vc)
    one, zero = np.ones_like(d1), np.zeros_like(d1)
    regions = [
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (d6 >= 0) & (d5 <= d6),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
    ]
    v = np.select(regions, [zero, one, zero, t_ab, zero, 1.0 - t_bc], default=vb * inside)
    w = np.select(regions, [zero, zero, one, zero, t_ac, t_bc], default=vc * inside)
    weights = np.column_stack([1.0 - v - w, v, w])
    return weights[:, :1] * a + weights[:, 1:2] * b + weights[:, 2:] * c, weights


def nearest_triangles(points: Floats, vertices: Floats, faces: Ints) -> tuple[Floats, Ints, Floats]:
    """For each point: its distance to the surface (vertices, faces), the nearest triangle (the lowest
    index among equally near ones) and the barycentric coordinates of the nearest point on it.

    Triangles are found through a grid of their boxes grown by a margin; a point whose nearest triangle
    lies beyond the margin is searched again with twice the margin, so the answer is exact."""
    tri = vertices[faces]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    distance = np.full(len(points), np.inf)
    nearest = np.full(len(points), -1, dtype=np.int64)
    weights = np.zeros((len(points), 3))
    margin = float(np.mean(np.max(hi - lo, axis=1)))
    todo = np.arange(len(points))
    while len(todo):
        p, t = grid.points_in_boxes(points[todo], lo - margin, hi + margin)
        closest, w = closest_points(points[todo][p], tri[t, 0], tri[t, 1], tri[t, 2])
        d = np.linalg.norm(closest - points[todo][p], axis=1)
        # Per point, the nearest candidate (ties: the lowest triangle index, for determinism).
        order = np.lexsort((t, d, p))
        p, t, d, w = p[order], t[order], d[order], w[order]
        first = np.flatnonzero(np.r_[True, p[1:] != p[:-1]])
        found = todo[p[first]]
        distance[found], nearest[found], weights[found] = d[first], t[first], w[first]
        # Only a nearest triangle within the margin is sure to be the nearest of all.
        todo = todo[distance[todo] > margin]
        margin *= 2.0
    return distance, nearest, weights


def orient3d(a: Floats, b: Floats, c: Floats, d: Floats) -> Floats:
    """Six times the signed volume of (a, b, c, d): positive when d lies above abc (right-hand rule)."""
    return _dot(np.cross(b - a, c - a), d - a)


def _orient2d(a: Floats, b: Floats, c: Floats) -> Floats:
    return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])


# Orientation volumes (lengths³) and areas (lengths²) within this fraction of the local size's power
# count as zero: touching counts as meeting, and rounding does not hide a contact.
RELATIVE_ZERO = 1e-10


def segments_meet_triangles(p: Floats, q: Floats, a: Floats, b: Floats, c: Floats) -> Bools:
    """Whether each segment pq meets (crosses or touches) its triangle abc."""
    size = np.max(np.linalg.norm(np.stack([q - p, b - a, c - a, p - a]), axis=2), axis=0)
    zero = RELATIVE_ZERO * size**3
    sp, sq = orient3d(a, b, c, p), orient3d(a, b, c, q)
    coplanar = (np.abs(sp) <= zero) & (np.abs(sq) <= zero)
    straddles = ~(((sp > zero) & (sq > zero)) | ((sp < -zero) & (sq < -zero)))
    s1, s2, s3 = orient3d(p, q, a, b), orient3d(p, q, b, c), orient3d(p, q, c, a)
    through = ((s1 >= -zero) & (s2 >= -zero) & (s3 >= -zero)) | ((s1 <= zero) & (s2 <= zero) & (s3 <= zero))
    meets: Bools = straddles & ~coplanar & through
    if np.any(coplanar):
        rows = np.flatnonzero(coplanar)
        meets[rows] = _coplanar_segments_meet(p[rows], q[rows], a[rows], b[rows], c[rows], size[rows])
    return meets


def _coplanar_segments_meet(p: Floats, q: Floats, a: Floats, b: Floats, c: Floats, size: Floats) -> Bools:
    """The same question in the triangle's plane, projected along its normal's largest component."""
    axis = np.argmax(np.abs(np.cross(b - a, c - a)), axis=1)
    keep = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    rows = np.arange(len(p))[:, None]
    p2, q2, a2, b2, c2 = (x[rows, keep] for x in (p, q, a, b, c))
    zero, slack = RELATIVE_ZERO * size**2, (RELATIVE_ZERO * size)[:, None]
    sign = np.sign(_orient2d(a2, b2, c2))

    def inside(x: Floats) -> Bools:
        return (
            (sign * _orient2d(a2, b2, x) >= -zero)
            & (sign * _orient2d(b2, c2, x) >= -zero)
            & (sign * _orient2d(c2, a2, x) >= -zero)
        )

    def on(x: Floats, s: Floats, t: Floats) -> Bools:
        """Whether x, known to lie on the line st, lies on the segment st."""
        within: Bools = np.all((np.minimum(s, t) - slack <= x) & (x <= np.maximum(s, t) + slack), axis=1)
        return within

    def crosses(u: Floats, v: Floats) -> Bools:
        o1, o2 = _orient2d(p2, q2, u), _orient2d(p2, q2, v)
        o3, o4 = _orient2d(u, v, p2), _orient2d(u, v, q2)
        proper = (o1 * o2 < 0) & (o3 * o4 < 0)
        touching = (
            ((np.abs(o1) <= zero) & on(u, p2, q2))
            | ((np.abs(o2) <= zero) & on(v, p2, q2))
            | ((np.abs(o3) <= zero) & on(p2, u, v))
            | ((np.abs(o4) <= zero) & on(q2, u, v))
        )
        return proper | touching

    return inside(p2) | inside(q2) | crosses(a2, b2) | crosses(b2, c2) | crosses(c2, a2)
