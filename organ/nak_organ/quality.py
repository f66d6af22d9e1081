"""Tetrahedra's volumes and shape quality.

Quality is the normalized radius ratio γ = 3 r / R (inradius over circumradius): 1 for a regular
tetrahedron, 0 for a flat one. It is gmsh's "gamma" and the reciprocal of the aspect ratio that
`nak mesh info` prints (circumradius / (3 × inradius)).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Floats = NDArray[np.float64]
Ints = NDArray[np.int64]


def tet_volumes(nodes: Floats, tets: Ints) -> Floats:
    a, b, c, d = (nodes[tets[:, k]] for k in range(4))
    volumes: Floats = np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0
    return volumes


def radius_ratios(nodes: Floats, tets: Ints) -> Floats:
    a, b, c, d = (nodes[tets[:, k]] for k in range(4))
    u, v, w = b - a, c - a, d - a
    six_volume = np.einsum("ij,ij->i", u, np.cross(v, w))
    faces = (np.cross(u, v), np.cross(v, w), np.cross(w, u), np.cross(c - b, d - b))
    area = 0.5 * sum(np.linalg.norm(f, axis=1) for f in faces)
    inradius = 0.5 * np.abs(six_volume) / area  # r = 3V / A
    # The circumcentre relative to a (the tetrahedron's own formula, from |x - a| = |x - b| = …).
    centre = (
        np.sum(u * u, axis=1)[:, None] * np.cross(v, w)
        + np.sum(v * v, axis=1)[:, None] * np.cross(w, u)
        + np.sum(w * w, axis=1)[:, None] * np.cross(u, v)
    ) / (2.0 * six_volume[:, None])
    circumradius = np.linalg.norm(centre, axis=1)
    return np.asarray(3.0 * inradius / circumradius, dtype=np.float64)
