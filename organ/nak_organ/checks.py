"""What a surface must be before it is meshed, and the refusals that say where it is not.

A surface that encloses one organ is closed (every edge in exactly two faces), manifold (around every
vertex one fan of faces), consistently oriented, one shell, free of degenerate and self-intersecting
faces, and of an organ's size once its units are applied. Each failed check is one line that names the
file, what is wrong, how often, and one place (a vertex, a face, an edge) to look at. Nothing is
repaired: a surface that fails goes back to its segmentation tool (or to a repair tool such as MeshFix).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .errors import OrganInputError
from .geometry import face_normals
from .graphs import Edges, connected_components, surface_edges
from .intersections import intersecting_pairs
from .reading import METRES_PER_UNIT, Surface

Floats = NDArray[np.float64]
Ints = NDArray[np.int64]

# Bounding-box diagonals of organs, metres: from a small kidney or gallbladder to a large liver.
ORGAN_DIAGONAL_M = (0.02, 0.60)

# A face whose height is below this fraction of its longest edge has collapsed to a segment or a point.
DEGENERATE_HEIGHT = 1e-9


def check_surface(surface: Surface) -> None:
    """Raises OrganInputError with every problem found; returns when the surface can be meshed."""
    problems = _size_problems(surface)
    degenerate = _degenerate_problems(surface)
    if degenerate:
        # The other checks would mostly report the collapsed faces again, as open or crowded edges.
        problems += degenerate
    else:
        edges = surface_edges(surface.faces)
        problems += _edge_problems(surface, edges)
        problems += _pinched_vertex_problems(surface, edges)
        problems += _shell_problems(surface, edges)
        problems += _intersection_problems(surface)
    if problems:
        raise OrganInputError([f"{surface.path}: {p}" for p in problems])


def _count(n: int, one: str, many: str) -> str:
    return f"{n} {one if n == 1 else many}"


def bounding_diagonal(vertices: Floats) -> float:
    return float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))


def _length(metres: float) -> str:
    if metres >= 1.0:
        return f"{metres:.3g} m"
    if metres >= 0.01:
        return f"{metres * 100:.3g} cm"
    return f"{metres * 1000:.3g} mm"


def _size_problems(surface: Surface) -> list[str]:
    low, high = ORGAN_DIAGONAL_M
    diagonal = bounding_diagonal(surface.vertices)
    if low <= diagonal <= high:
        return []
    in_file_units = diagonal / METRES_PER_UNIT[surface.units]
    fits = [u for u, scale in METRES_PER_UNIT.items() if low <= in_file_units * scale <= high]
    advice = (
        f"the coordinates look like {' or '.join(fits)}: pass --units {fits[0]} "
        f"(which makes it {_length(in_file_units * METRES_PER_UNIT[fits[0]])})"
        if fits
        else "no unit (mm, cm, m) gives an organ's size: check the file's scale"
    )
    adjective = "large" if diagonal > high else "small"
    return [
        f"with --units {surface.units} the surface is {_length(diagonal)} across (bounding-box diagonal), too "
        f"{adjective} for an organ ({_length(low)} to {_length(high)}): {advice}"
    ]


def _degenerate_problems(surface: Surface) -> list[str]:
    faces, vertices = surface.faces, surface.vertices
    corners = vertices[faces]
    longest = np.max(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2), axis=1)
    height = np.linalg.norm(face_normals(vertices, faces), axis=1) / np.maximum(longest, np.finfo(float).tiny)
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
    bad = np.flatnonzero(repeated | (height <= DEGENERATE_HEIGHT * longest))
    if not len(bad):
        return []
    f = int(bad[0])
    return [
        f"{_count(len(bad), 'degenerate face', 'degenerate faces')} (no area: a repeated or collinear vertex), "
        f"e.g. face {surface.face_ids[f]} with {', '.join(surface.vertex(int(v)) for v in faces[f])}"
    ]


def _edge(surface: Surface, edges: Edges, edge: int) -> str:
    a, b = edges.vertices[edge]
    faces = [str(surface.face_ids[f]) for f in edges.faces_of(edge)]
    named = f"face {faces[0]}" if len(faces) == 1 else f"faces {', '.join(faces)}"
    return f"the edge from {surface.vertex(int(a))} to {surface.vertex(int(b))} ({named})"


def _edge_problems(surface: Surface, edges: Edges) -> list[str]:
    problems = []
    open_edges = np.flatnonzero(edges.face_count == 1)
    if len(open_edges):
        problems.append(
            f"the surface is open: {_count(len(open_edges), 'edge belongs', 'edges belong')} to one face only, e.g. "
            f"{_edge(surface, edges, int(open_edges[0]))}; close the hole before meshing"
        )
    crowded = np.flatnonzero(edges.face_count > 2)
    if len(crowded):
        problems.append(
            f"the surface is not manifold: {_count(len(crowded), 'edge is', 'edges are')} shared by more than two "
            f"faces, e.g. {_edge(surface, edges, int(crowded[0]))}"
        )
    # Two faces that agree on which side is outside traverse their shared edge in opposite directions.
    pairs = np.flatnonzero(edges.face_count == 2)
    first = edges.half_edges[edges.first_half_edge[pairs]]
    second = edges.half_edges[edges.first_half_edge[pairs] + 1]
    flipped = pairs[first[:, 0] == second[:, 0]]
    if len(flipped):
        problems.append(
            f"the faces are not consistently oriented: {_count(len(flipped), 'edge is', 'edges are')} traversed in "
            f"the same direction by both their faces, e.g. {_edge(surface, edges, int(flipped[0]))}"
        )
    return problems


def _pinched_vertex_problems(surface: Surface, edges: Edges) -> list[str]:
    """Vertices whose faces form several fans (two cones touching at their tips): the corners of a
    vertex's faces, joined across the edges two faces share, make one group per fan."""
    faces = surface.faces
    pairs = np.flatnonzero(edges.face_count == 2)
    rows = edges.first_half_edge[pairs]
    f, g = edges.half_edges[rows, 2], edges.half_edges[rows + 1, 2]

    def corner(face: Ints, vertex: Ints) -> Ints:
        index: Ints = 3 * face + np.argmax(faces[face] == vertex[:, None], axis=1)
        return index

    u, v = [], []
    for end in (0, 1):
        vertex = edges.vertices[pairs, end]
        u.append(corner(f, vertex))
        v.append(corner(g, vertex))
    fans = connected_components(3 * len(faces), np.concatenate(u), np.concatenate(v))
    vertex_fan = np.unique(np.column_stack([faces.ravel(), fans]), axis=0)
    fan_count = np.bincount(vertex_fan[:, 0], minlength=len(surface.vertices))
    pinched = np.flatnonzero(fan_count > 1)
    if not len(pinched):
        return []
    worst = int(pinched[0])
    return [
        f"the surface is not manifold: {_count(len(pinched), 'vertex joins', 'vertices join')} separate fans of "
        f"faces (the surface touches itself there), e.g. {surface.vertex(worst)} with {fan_count[worst]} fans"
    ]


def _shell_problems(surface: Surface, edges: Edges) -> list[str]:
    halves = edges.half_edges
    same_edge = np.repeat(np.arange(len(edges.vertices)), edges.face_count)
    # Faces are joined when they share an edge: link each half-edge's face to its edge's first face.
    first_face = halves[edges.first_half_edge[same_edge], 2]
    shells = connected_components(len(surface.faces), halves[:, 2], first_face)
    count = int(shells.max()) + 1
    if count == 1:
        return []
    sizes = np.bincount(shells)
    order = np.argsort(-sizes, kind="stable")[:4]
    listed = ", ".join(f"{sizes[s]} faces with face {surface.face_ids[int(np.argmax(shells == s))]}" for s in order)
    more = "" if count <= 4 else ", …"
    return [
        f"the surface has {count} separate shells ({listed}{more}): mesh one closed organ per file; "
        "remove stray pieces in the segmentation tool"
    ]


def _intersection_problems(surface: Surface) -> list[str]:
    pairs = intersecting_pairs(surface.vertices, surface.faces)
    if not len(pairs):
        return []
    f, g = (int(x) for x in pairs[0])
    where = surface.point(surface.vertices[surface.faces[f]].mean(axis=0))
    return [
        f"the surface intersects itself: {_count(len(pairs), 'pair', 'pairs')} of faces cross, e.g. faces "
        f"{surface.face_ids[f]} and {surface.face_ids[g]} near {where}"
    ]
