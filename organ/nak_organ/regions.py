"""Automatic grasp regions: the free surface split into regions of similar area.

The free surface is the boundary nodes that are neither fixed nor next to a fixed node (sharing a
boundary triangle with one), so no grasp pulls right beside a fixed node. Its nodes are clustered by
k-means on their positions, each node weighted by the area it stands for, from a k-means++ start with a
fixed seed: deterministic, and on a surface of even node density its clusters are patches of similar
area. A cluster that falls apart into pieces (k-means sees distances through the organ, not along its
surface) keeps its largest piece; each smaller piece joins the neighbouring cluster it shares most
edges with. Regions are numbered by their centres, in x then y then z.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .boundary import Boundary
from .errors import OrganInputError
from .graphs import connected_components, vertex_neighbours
from .selections import NodeSet

Floats = NDArray[np.float64]
Ints = NDArray[np.int64]
Bools = NDArray[np.bool_]

SEED = 1
MAX_ITERATIONS = 200
# The largest region's area over the smallest's that balancing aims at, and its step (per unit of
# relative area excess, in units of the mean squared distance of nodes to their centres).
AREA_BALANCE = 1.2
BIAS_STEP = 0.5


def free_surface(boundary: Boundary, fixed: NodeSet) -> Bools:
    """Per boundary node: whether it is neither fixed nor shares a boundary triangle with a fixed node."""
    is_fixed = np.isin(boundary.nodes, fixed.nodes)
    near_fixed = np.zeros(len(boundary.nodes), dtype=bool)
    near_fixed[boundary.triangles[np.any(is_fixed[boundary.triangles], axis=1)].ravel()] = True
    return ~near_fixed


def split_free_surface(boundary: Boundary, fixed: NodeSet, count: int) -> list[NodeSet]:
    """`count` regions grasp_01, grasp_02, … that together hold the whole free surface."""
    free = np.flatnonzero(free_surface(boundary, fixed))
    if len(free) < count:
        raise OrganInputError(
            [
                f"--grasp-regions {count}: the free surface (not fixed, not next to fixed) has {len(free)} "
                "nodes; fix less, ask for fewer regions or for more nodes (--target-nodes)"
            ]
        )
    positions, areas = boundary.positions[free], boundary.areas[free]
    labels = _kmeans(positions, areas, count)
    u, v = vertex_neighbours(boundary.triangles)
    index = np.full(len(boundary.nodes), -1, dtype=np.int64)
    index[free] = np.arange(len(free))
    both_free = (index[u] >= 0) & (index[v] >= 0)
    labels = _join_stray_pieces(labels, areas, index[u[both_free]], index[v[both_free]])
    centres = np.array([np.average(positions[labels == k], axis=0, weights=areas[labels == k]) for k in range(count)])
    order = np.lexsort(centres.T[::-1])
    regions = []
    for number, k in enumerate(order, start=1):
        nodes = boundary.nodes[free[labels == k]]
        name = f"grasp_{number:02d}"
        regions.append(NodeSet(name, nodes, ((f"automatic region {name}", nodes),)))
    return regions


def _kmeans(points: Floats, weights: Floats, count: int) -> Ints:
    """Weighted k-means (Lloyd) from a weighted k-means++ start; labels 0 … count-1."""
    rng = np.random.default_rng(SEED)
    centres = [points[rng.choice(len(points), p=weights / weights.sum())]]
    nearest = np.sum((points - centres[0]) ** 2, axis=1)
    for _ in range(1, count):
        chance = weights * nearest
        centres.append(points[rng.choice(len(points), p=chance / chance.sum())])
        nearest = np.minimum(nearest, np.sum((points - centres[-1]) ** 2, axis=1))
    centre = np.array(centres)
    labels = np.full(len(points), -1, dtype=np.int64)
    for _ in range(MAX_ITERATIONS):
        new = np.argmin(np.sum((points[:, None, :] - centre[None, :, :]) ** 2, axis=2), axis=1)
        if np.array_equal(new, labels):
            break
        labels = new
        _update_centres(centre, points, weights, labels)
    return _balance(points, weights, centre, labels)


def _update_centres(centre: Floats, points: Floats, weights: Floats, labels: Ints) -> None:
    for k in range(len(centre)):
        members = labels == k
        if np.any(members):
            centre[k] = np.average(points[members], axis=0, weights=weights[members])


def _balance(points: Floats, weights: Floats, centre: Floats, labels: Ints) -> Ints:
    """Evens out the clusters' areas: each node joins the centre with the least squared distance minus
    that cluster's bias, and biases fall for clusters above the mean area and rise for those below (a
    power diagram), until the largest is within AREA_BALANCE of the smallest."""
    count = len(centre)
    distance = np.sum((points[:, None, :] - centre[None, :, :]) ** 2, axis=2)
    scale = float(np.mean(distance[np.arange(len(points)), labels]))
    bias = np.zeros(count)
    for _ in range(MAX_ITERATIONS):
        area = np.bincount(labels, weights=weights, minlength=count)
        if area.min() > 0 and area.max() <= AREA_BALANCE * area.min():
            break
        bias -= BIAS_STEP * scale * (area / area.mean() - 1.0)
        _update_centres(centre, points, weights, labels)
        distance = np.sum((points[:, None, :] - centre[None, :, :]) ** 2, axis=2)
        labels = np.argmin(distance - bias, axis=1)
    return labels


def _join_stray_pieces(labels: Ints, areas: Floats, u: Ints, v: Ints) -> Ints:
    """Each cluster keeps its largest connected piece; the others join the neighbouring cluster they
    share most edges with (a piece with no other cluster beside it stays)."""
    labels = labels.copy()
    for _ in range(len(np.unique(labels)) + 1):
        same = labels[u] == labels[v]
        pieces = connected_components(len(labels), u[same], v[same])
        piece_area = np.bincount(pieces, weights=areas)
        piece_label = np.zeros(len(piece_area), dtype=np.int64)
        piece_label[pieces] = labels
        # The largest piece of each cluster (ties: the lowest piece).
        order = np.lexsort((np.arange(len(piece_area)), -piece_area, piece_label))
        main = order[np.r_[True, piece_label[order][1:] != piece_label[order][:-1]]]
        stray = np.ones(len(piece_area), dtype=bool)
        stray[main] = False
        crossing = stray[pieces[u]] & (labels[u] != labels[v])
        if not np.any(crossing):
            break
        # Per stray piece, the neighbouring cluster across most edges (ties: the lowest label).
        pairs, shared = np.unique(
            np.column_stack([pieces[u][crossing], labels[v][crossing]]), axis=0, return_counts=True
        )
        best = pairs[np.lexsort((pairs[:, 1], -shared, pairs[:, 0]))]
        best = best[np.r_[True, best[1:, 0] != best[:-1, 0]]]
        target = np.full(len(piece_area), -1, dtype=np.int64)
        target[best[:, 0]] = best[:, 1]
        moved = target[pieces] >= 0
        labels[moved] = target[pieces][moved]
    return labels
