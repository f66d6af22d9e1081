"""Connectivity of triangle surfaces: their edges and the connected pieces of a graph."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Ints = NDArray[np.int64]


def connected_components(count: int, u: Ints, v: Ints) -> Ints:
    """A component label per node of the graph with `count` nodes and edges (u, v): 0, 1, … in the
    order of each component's lowest node.

    Union by hooking each edge's larger root under its smaller one, then pointer jumping until every
    node points at its root; a few rounds suffice, each one numpy pass over the edges."""
    parent = np.arange(count, dtype=np.int64)
    while True:
        pu, pv = parent[u], parent[v]
        differ = pu != pv
        if not np.any(differ):
            break
        low = np.minimum(pu, pv)[differ]
        np.minimum.at(parent, pu[differ], low)
        np.minimum.at(parent, pv[differ], low)
        while True:
            grand = parent[parent]
            if np.array_equal(grand, parent):
                break
            parent = grand
    # Roots are each component's lowest node, so ranking them orders components by it.
    _, labels = np.unique(parent, return_inverse=True)
    return labels.astype(np.int64)


@dataclass(frozen=True)
class Edges:
    """The undirected edges of a triangle surface and the faces around each."""

    vertices: Ints
    """(E, 2) vertex pairs, lower index first, sorted."""
    face_count: Ints
    """(E,) how many faces use each edge: 2 on a closed manifold surface."""
    half_edges: Ints
    """(3F, 3) rows (from, to, face) of each face's directed edges, grouped by edge in `vertices` order."""
    first_half_edge: Ints
    """(E,) where each edge's rows start in `half_edges`."""

    def faces_of(self, edge: int) -> Ints:
        start = self.first_half_edge[edge]
        return self.half_edges[start : start + self.face_count[edge], 2]


def surface_edges(faces: Ints) -> Edges:
    start, end = faces.ravel(), np.roll(faces, -1, axis=1).ravel()
    face = np.repeat(np.arange(len(faces), dtype=np.int64), 3)
    low, high = np.minimum(start, end), np.maximum(start, end)
    order = np.lexsort((face, high, low))
    pairs = np.column_stack([low, high])[order]
    new = np.r_[True, np.any(pairs[1:] != pairs[:-1], axis=1)]
    first = np.flatnonzero(new)
    return Edges(
        vertices=pairs[first],
        face_count=np.diff(np.r_[first, len(pairs)]),
        half_edges=np.column_stack([start, end, face])[order],
        first_half_edge=first,
    )


def vertex_neighbours(faces: Ints) -> tuple[Ints, Ints]:
    """Each edge of the surface in both directions, as (from, to) arrays."""
    edges = surface_edges(faces).vertices
    return np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]]
