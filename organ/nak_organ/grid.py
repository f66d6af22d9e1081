"""A uniform grid over axis-aligned boxes: which boxes overlap, and which boxes hold which points.

The self-intersection test and the distance queries would otherwise compare every triangle with every
other (20,000 triangles: 2 × 10⁸ pairs). Each box is entered into the cells it covers; only boxes that
share a cell are compared, and only pairs whose boxes really overlap are returned.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Floats = NDArray[np.float64]
Ints = NDArray[np.int64]


def overlapping_boxes(lo: Floats, hi: Floats) -> tuple[Ints, Ints]:
    """Pairs (i, j), i < j, of boxes [lo, hi] that overlap, sorted."""
    cell = _cell_size(lo, hi)
    origin = lo.min(axis=0)
    keys, boxes = _cells_of_boxes(lo, hi, origin, cell, _grid_shape(hi.max(axis=0), origin, cell))
    order = np.lexsort((boxes, keys))
    keys, boxes = keys[order], boxes[order]
    # Each entry pairs with the entries after it in the same cell.
    group_end = np.searchsorted(keys, keys, side="right")
    after = group_end - np.arange(len(keys)) - 1
    first = np.repeat(np.arange(len(keys)), after)
    step = np.arange(len(first)) - np.repeat(np.cumsum(after) - after, after) + 1
    i, j = boxes[first], boxes[first + step]
    i, j = np.minimum(i, j), np.maximum(i, j)
    overlap = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1) & (i != j)
    pair_keys = np.unique(i[overlap] * len(lo) + j[overlap])
    return pair_keys // len(lo), pair_keys % len(lo)


def points_in_boxes(points: Floats, lo: Floats, hi: Floats) -> tuple[Ints, Ints]:
    """Pairs (point p, box b) with p inside box b, sorted by point."""
    cell = _cell_size(lo, hi)
    origin = np.minimum(lo.min(axis=0), points.min(axis=0))
    shape = _grid_shape(np.maximum(hi.max(axis=0), points.max(axis=0)), origin, cell)
    keys, boxes = _cells_of_boxes(lo, hi, origin, cell, shape)
    order = np.argsort(keys, kind="stable")
    keys, boxes = keys[order], boxes[order]
    point_keys = _key(np.floor((points - origin) / cell).astype(np.int64), shape)
    start = np.searchsorted(keys, point_keys, side="left")
    count = np.searchsorted(keys, point_keys, side="right") - start
    p = np.repeat(np.arange(len(points)), count)
    entry = np.arange(len(p)) - np.repeat(np.cumsum(count) - count, count) + np.repeat(start, count)
    b = boxes[entry]
    inside = np.all((lo[b] <= points[p]) & (points[p] <= hi[b]), axis=1)
    return p[inside], b[inside]


def _cell_size(lo: Floats, hi: Floats) -> float:
    # About the size of a typical box: each box covers a few cells and each cell holds a few boxes.
    extent = float(np.mean(np.max(hi - lo, axis=1)))
    span = float(np.max(hi.max(axis=0) - lo.min(axis=0)))
    return max(extent, span / 500.0, 1e-12)


def _grid_shape(top: Floats, origin: Floats, cell: float) -> Ints:
    """Cells along each axis for a grid from `origin` to `top`."""
    return np.floor((top - origin) / cell).astype(np.int64) + 1


def _key(cells: Ints, shape: Ints) -> Ints:
    key: Ints = cells[:, 0] + shape[0] * (cells[:, 1] + shape[1] * cells[:, 2])
    return key


def _cells_of_boxes(lo: Floats, hi: Floats, origin: Floats, cell: float, shape: Ints) -> tuple[Ints, Ints]:
    """(cell key, box) for every cell each box covers."""
    first = np.floor((lo - origin) / cell).astype(np.int64)
    last = np.floor((hi - origin) / cell).astype(np.int64)
    span = last - first + 1
    count = np.prod(span, axis=1)
    box = np.repeat(np.arange(len(lo)), count)
    k = np.arange(len(box)) - np.repeat(np.cumsum(count) - count, count)
    sx, sy = span[box, 0], span[box, 1]
    cells = first[box] + np.column_stack([k % sx, (k // sx) % sy, k // (sx * sy)])
    return _key(cells, shape), box
