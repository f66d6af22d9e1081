"""The volume mesh's boundary surface, matched to the input surface it was made from.

Selections choose among the boundary's nodes, the automatic grasp regions split it, and the summary
reports how far it strays from the input: each boundary node's distance to the input surface (gmsh
places them on the input's triangles, so this is rounding) and each input vertex's distance to the
boundary (what the coarser triangles cut off: flattened bumps and rounded edges).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .geometry import face_areas, nearest_triangles
from .meshing import VolumeMesh
from .reading import Surface

Floats = NDArray[np.float64]
Ints = NDArray[np.int64]


@dataclass(frozen=True)
class Boundary:
    nodes: Ints
    """Mesh indices of the boundary nodes, sorted."""
    positions: Floats
    """(S, 3) their positions, metres."""
    triangles: Ints
    """(B, 3) boundary triangles as indices into `nodes` (not mesh indices)."""
    areas: Floats
    """(S,) a third of the area of each node's triangles: the surface each node stands for."""
    input_face: Ints
    """(S,) the input triangle nearest each node."""
    input_weights: Floats
    """(S, 3) barycentric coordinates of the nearest point on that triangle."""
    node_deviation: float
    """Largest distance of a boundary node from the input surface (metres)."""
    input_deviation: float
    """Largest distance of an input vertex from the boundary (metres)."""


def match_boundary(mesh: VolumeMesh, surface: Surface) -> Boundary:
    nodes = np.unique(mesh.boundary)
    triangles = np.searchsorted(nodes, mesh.boundary)
    positions = mesh.nodes[nodes]
    thirds = np.repeat(face_areas(positions, triangles) / 3.0, 3)
    areas = np.bincount(triangles.ravel(), weights=thirds, minlength=len(nodes)).astype(np.float64)
    distance, face, weights = nearest_triangles(positions, surface.vertices, surface.faces)
    back, _, _ = nearest_triangles(surface.vertices, positions, triangles)
    return Boundary(
        nodes=nodes,
        positions=positions,
        triangles=triangles,
        areas=areas,
        input_face=face,
        input_weights=weights,
        node_deviation=float(distance.max()),
        input_deviation=float(back.max()),
    )
