"""Tetrahedralizing a checked surface with gmsh, to about a target number of nodes.

As gmsh's tutorial t13 remeshes an STL without CAD: the surface becomes a discrete entity, gmsh
classifies it into patches split at sharp edges (`classifySurfaces`) and parametrizes each
(`createGeometry`), a surface loop bounds one volume, and `generate(3)` remeshes the surface and fills
the volume at a uniform element size. The size is chosen from the enclosed volume, then corrected from the
node count each try gives, until the count is within NODE_TOLERANCE of the target. gmsh runs on one
thread with a fixed seed, so the same surface and options give the same mesh.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import gmsh
import numpy as np
from numpy.typing import NDArray

from .errors import OrganInputError
from .geometry import enclosed_volume
from .reading import Surface

Floats = NDArray[np.float64]
Ints = NDArray[np.int64]

# Nodes per volume in units of the element size cubed, a first guess that the tries correct: 0.82 on an
# ellipsoid (9,686 nodes at 4.40 mm in 1,003 mL), 0.87 on a two-lobed shape (9,753 at 3.01 mm in 306 mL).
NODES_PER_SIZE_CUBED = 0.85
NODE_TOLERANCE = 0.10
MAX_TRIES = 4


@dataclass(frozen=True)
class VolumeMesh:
    nodes: Floats
    """(N, 3) positions in metres."""
    tets: Ints
    """(T, 4) node indices, positively oriented (the fourth node above the first three's right-hand normal)."""
    boundary: Ints
    """(B, 3) boundary triangles, counter-clockwise seen from outside."""
    element_size: float
    """The target edge length the mesh was made with (metres)."""
    tries: tuple[tuple[float, int], ...]
    """(element size, node count) of every try, in order."""


def tetrahedralize(surface: Surface, target_nodes: int, feature_angle_deg: float) -> VolumeMesh:
    """A linear tetrahedral mesh of the volume `surface` encloses, with about `target_nodes` nodes."""
    volume = abs(enclosed_volume(surface.vertices, surface.faces))
    size = (NODES_PER_SIZE_CUBED * volume / target_nodes) ** (1.0 / 3.0)
    gmsh.initialize(interruptible=False)
    try:
        _configure()
        _volume_from_surface(surface, feature_angle_deg)
        results: list[tuple[float, Floats, Ints]] = []
        for _ in range(MAX_TRIES):
            nodes, tets = _mesh(size, surface)
            results.append((size, nodes, tets))
            if abs(len(nodes) / target_nodes - 1.0) <= NODE_TOLERANCE:
                break
            size = _next_size([(h, len(n)) for h, n, _ in results], target_nodes)
    finally:
        gmsh.finalize()
    size, nodes, tets = min(results, key=lambda r: abs(len(r[1]) - target_nodes))
    tries = tuple((h, len(n)) for h, n, _ in results)
    return VolumeMesh(nodes, tets, boundary_triangles(tets), size, tries)


def _configure() -> None:
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.option.setNumber("General.NumThreads", 1)
    gmsh.option.setNumber("Mesh.RandomSeed", 1)
    # A uniform size: neither the discrete surface's points nor its curvature refine it.
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    # Delaunay in 2D: gmsh's default, Frontal-Delaunay, took 10 s instead of 0.1 s to remesh a
    # 20,000-triangle surface at one element size (3.3253 mm on the two-lobed test shape).
    gmsh.option.setNumber("Mesh.Algorithm", 5)
    # Delaunay in 3D with gmsh's and Netgen's optimizers, as for the phantom.
    gmsh.option.setNumber("Mesh.Algorithm3D", 1)
    gmsh.option.setNumber("Mesh.Optimize", 1)
    gmsh.option.setNumber("Mesh.OptimizeNetgen", 1)


def _volume_from_surface(surface: Surface, feature_angle_deg: float) -> None:
    gmsh.model.add("organ")
    entity = gmsh.model.addDiscreteEntity(2)
    tags = np.arange(1, len(surface.vertices) + 1)
    gmsh.model.mesh.addNodes(2, entity, tags.tolist(), surface.vertices.ravel().tolist())
    gmsh.model.mesh.addElementsByType(entity, 2, [], (surface.faces + 1).ravel().tolist())
    # Patches split where faces meet at more than the feature angle; each parametrizable (third argument),
    # and their boundary curves kept whole (curve angle π).
    gmsh.model.mesh.classifySurfaces(math.radians(feature_angle_deg), True, True, math.pi)
    gmsh.model.mesh.createGeometry()
    patches = [tag for _, tag in gmsh.model.getEntities(2)]
    loop = gmsh.model.geo.addSurfaceLoop(patches)
    gmsh.model.geo.addVolume([loop])
    gmsh.model.geo.synchronize()


def _mesh(size: float, surface: Surface) -> tuple[Floats, Ints]:
    gmsh.model.mesh.clear()
    gmsh.option.setNumber("Mesh.MeshSizeMax", size)
    gmsh.option.setNumber("Mesh.MeshSizeMin", size)
    try:
        gmsh.model.mesh.generate(3)
    except Exception as e:  # gmsh raises a bare Exception with its last error
        raise OrganInputError(
            [f"{surface.path}: gmsh could not mesh the surface at element size {size * 1000:.3g} mm: {e}"]
        ) from None
    tags, coords, _ = gmsh.model.mesh.getNodes()
    tet_tags, tet_nodes = gmsh.model.mesh.getElementsByType(4)
    if len(tet_tags) == 0:
        raise OrganInputError([f"{surface.path}: gmsh made no tetrahedra (is the surface closed?)"])
    # Keep the nodes tetrahedra use, in gmsh's order, numbered from 0.
    used = np.unique(tet_nodes)
    order = np.flatnonzero(np.isin(tags, used))
    index = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    index[tags[order]] = np.arange(len(order))
    nodes = coords.reshape(-1, 3)[order]
    tets = index[tet_nodes.astype(np.int64)].reshape(-1, 4)
    return nodes, tets


def _next_size(tries: list[tuple[float, int]], target: int) -> float:
    """The element size expected to give `target` nodes: the node count goes as size^-k, with k = 3 for
    a first correction (the volume's nodes dominate) and k fitted to the last two tries after that."""
    (h1, n1) = tries[-1]
    k = 3.0
    if len(tries) >= 2:
        (h0, n0) = tries[-2]
        if h0 != h1 and n0 != n1:
            k = float(np.clip(-math.log(n1 / n0) / math.log(h1 / h0), 2.0, 3.0))
    return float(h1 * (n1 / target) ** (1.0 / k))


def boundary_triangles(tets: Ints) -> Ints:
    """Faces that belong to one tetrahedron only, oriented outwards."""
    # For a positively oriented (a, b, c, d), these faces have outward right-hand normals.
    faces = tets[:, [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]].reshape(-1, 3)
    keys = np.sort(faces, axis=1)
    _, first, counts = np.unique(keys, axis=0, return_index=True, return_counts=True)
    once: Ints = faces[np.sort(first[counts == 1])]
    return once
