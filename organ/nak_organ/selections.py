"""Node sets chosen by the user: `--fixed SPEC` (repeatable, their union) and `--grasp NAME=SPEC`.

A SPEC selects the boundary nodes of the output mesh it covers, in the input surface's own units:

* `sphere:x,y,z,r`: nodes within r of (x, y, z);
* `box:x0,y0,z0,x1,y1,z1`: nodes inside the axis-aligned box with these opposite corners;
* `vertices:i,j,…`: for each input vertex id, the boundary node nearest it;
* `group:NAME`: an OBJ's `g`/`o` group, or a PLY's vertex label value: the nodes whose nearest input
  face is in the group (OBJ), or whose nearest input vertex on that face carries the label (PLY).

Refused, each with the option at fault: a malformed SPEC, nothing fixed (the organ would float), a
selection that selects no node, and two node sets that share a node (naming both and one shared node).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .boundary import Boundary
from .errors import OrganInputError
from .reading import METRES_PER_UNIT, Surface

Floats = NDArray[np.float64]
Ints = NDArray[np.int64]

NODE_SET_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]*")


@dataclass(frozen=True)
class Selection:
    """One `--fixed` or `--grasp` argument, parsed."""

    option: str
    """The argument as given, e.g. "--fixed sphere:0,0,0,10", for messages."""
    node_set: str
    kind: str
    numbers: tuple[float, ...] = ()
    group: str = ""


@dataclass(frozen=True)
class NodeSet:
    name: str
    nodes: Ints
    """Sorted mesh node indices."""
    sources: tuple[tuple[str, Ints], ...]
    """Each selection that makes it up (its option text) and the nodes it selected."""


def parse_fixed(spec: str) -> Selection:
    return _parse(spec, f"--fixed {spec}", "fixed")


def parse_grasp(argument: str) -> Selection:
    name, equals, spec = argument.partition("=")
    option = f"--grasp {argument}"
    if not equals or not NODE_SET_NAME.fullmatch(name) or name == "fixed":
        raise OrganInputError(
            [f"{option}: expected NAME=SPEC with NAME a letter then letters, digits, _ or - (not 'fixed')"]
        )
    return _parse(spec, option, name)


_COUNTS = {"sphere": 4, "box": 6}


def _parse(spec: str, option: str, node_set: str) -> Selection:
    kind, colon, rest = spec.partition(":")
    if not colon or kind not in ("sphere", "box", "vertices", "group") or not rest:
        raise OrganInputError(
            [f"{option}: expected sphere:x,y,z,r, box:x0,y0,z0,x1,y1,z1, vertices:i,j,… or group:NAME"]
        )
    if kind == "group":
        return Selection(option, node_set, kind, group=rest)
    try:
        numbers = tuple(float(w) if kind != "vertices" else int(w) for w in rest.split(","))
    except ValueError:
        raise OrganInputError([f"{option}: {rest!r} is not a comma-separated list of numbers"]) from None
    if kind in _COUNTS and len(numbers) != _COUNTS[kind]:
        raise OrganInputError([f"{option}: a {kind} takes {_COUNTS[kind]} numbers, not {len(numbers)}"])
    if kind == "sphere" and numbers[3] <= 0:
        raise OrganInputError([f"{option}: the radius must be positive"])
    return Selection(option, node_set, kind, numbers=numbers)


def check_selections(fixed: list[Selection], grasps: list[Selection], surface: Surface) -> None:
    """What can be refused before meshing: nothing fixed, a grasp name given twice, an unknown group or
    vertex id. Raises OrganInputError with every problem found."""
    problems: list[str] = []
    if not fixed:
        problems.append(
            f"{surface.path}: nothing is fixed: give --fixed SPEC (where the organ is attached, e.g. the liver's "
            "bare area); an organ held by nothing would float away under the graspers"
        )
    names = [g.node_set for g in grasps]
    for name in sorted({n for n in names if names.count(n) > 1}):
        problems.append(f"--grasp {name}=…: the name {name!r} is given {names.count(name)} times")
    for selection in [*fixed, *grasps]:
        if selection.kind == "vertices":
            problems += _unknown_vertices(selection, surface)
        elif selection.kind == "group":
            problems += _unknown_group(selection, surface)
    if problems:
        raise OrganInputError(problems)


def node_sets(
    fixed: list[Selection], grasps: list[Selection], boundary: Boundary, surface: Surface
) -> tuple[NodeSet, list[NodeSet]]:
    """`fixed` and the grasp regions the selections make, after check_selections; raises
    OrganInputError for selections that select no node and node sets that overlap."""
    problems: list[str] = []
    selected: dict[str, list[tuple[str, Ints]]] = {}
    for selection in [*fixed, *grasps]:
        nodes, hint = _select(selection, boundary, surface)
        if len(nodes):
            selected.setdefault(selection.node_set, []).append((selection.option, nodes))
        else:
            problems.append(
                f"{selection.option} selects no boundary node of the mesh made from {surface.path.name}{hint}"
            )
    sets = [
        NodeSet(name, np.unique(np.concatenate([n for _, n in sources])), tuple(sources))
        for name, sources in selected.items()
    ]
    problems += _overlaps(sets, boundary, surface)
    if problems:
        raise OrganInputError(problems)
    return sets[0], sets[1:]  # `fixed` first: its selections come first


def _select(selection: Selection, boundary: Boundary, surface: Surface) -> tuple[Ints, str]:
    """The mesh nodes a selection selects, and a hint for when it selects none."""
    scale = METRES_PER_UNIT[surface.units]
    positions = boundary.positions
    numbers = np.array(selection.numbers, dtype=np.float64) * scale
    if selection.kind == "sphere":
        distance = np.linalg.norm(positions - numbers[:3], axis=1)
        chosen = distance <= numbers[3]
        hint = f"; the nearest boundary node is {distance.min() / scale:.4g} {surface.units} from its centre"
    elif selection.kind == "box":
        lo, hi = np.minimum(numbers[:3], numbers[3:]), np.maximum(numbers[:3], numbers[3:])
        chosen = np.all((lo <= positions) & (positions <= hi), axis=1)
        outside = np.linalg.norm(np.maximum(lo - positions, 0) + np.maximum(positions - hi, 0), axis=1)
        hint = f"; the nearest boundary node is {outside.min() / scale:.4g} {surface.units} outside it"
    elif selection.kind == "vertices":
        targets = surface.vertices[surface.id_to_vertex[np.array(selection.numbers, dtype=np.int64)]]
        distance = np.linalg.norm(positions[None, :, :] - targets[:, None, :], axis=2)
        chosen = np.zeros(len(positions), dtype=bool)
        chosen[np.argmin(distance, axis=1)] = True
        hint = ""
    else:
        chosen = _group_members(selection, boundary, surface)
        hint = "; the group is smaller than an element: make it larger or the mesh finer (--target-nodes)"
    return boundary.nodes[chosen], hint


def _unknown_vertices(selection: Selection, surface: Surface) -> list[str]:
    count = len(surface.id_to_vertex)
    unknown = [int(i) for i in selection.numbers if not 0 <= i < count or surface.id_to_vertex[int(i)] < 0]
    if not unknown:
        return []
    return [
        f"{selection.option}: {surface.path.name} has no vertex {unknown[0]} on a face (vertex ids run from 0 "
        f"to {count - 1})"
    ]


def _unknown_group(selection: Selection, surface: Surface) -> list[str]:
    if surface.group_names:
        if selection.group in surface.group_names:
            return []
        return [
            f"{selection.option}: {surface.path.name} has no group {selection.group!r}; its groups: "
            f"{', '.join(surface.group_names)}"
        ]
    if surface.vertex_labels is not None:
        values = np.unique(surface.vertex_labels)
        if re.fullmatch(r"-?\d+", selection.group) and int(selection.group) in values:
            return []
        return [
            f"{selection.option}: no vertex of {surface.path.name} has {surface.label_property} = "
            f"{selection.group}; its values: {', '.join(str(v) for v in values)}"
        ]
    return [f"{selection.option}: {surface.path.name} has no groups (OBJ g/o statements) or PLY vertex labels"]


def _group_members(selection: Selection, boundary: Boundary, surface: Surface) -> NDArray[np.bool_]:
    if surface.group_names:
        group = surface.group_names.index(selection.group)
        return np.asarray(surface.face_groups[boundary.input_face] == group)
    # A PLY label: the input vertex of the nearest face that lies nearest the node.
    assert surface.vertex_labels is not None
    corners = surface.faces[boundary.input_face]
    nearest_vertex = corners[np.arange(len(corners)), np.argmax(boundary.input_weights, axis=1)]
    return np.asarray(surface.vertex_labels[nearest_vertex] == int(selection.group))


def _overlaps(sets: list[NodeSet], boundary: Boundary, surface: Surface) -> list[str]:
    problems = []
    for k, a in enumerate(sets):
        for b in sets[k + 1 :]:
            shared = np.intersect1d(a.nodes, b.nodes)
            if not len(shared):
                continue
            node = int(shared[0])
            where = surface.point(boundary.positions[np.searchsorted(boundary.nodes, node)])
            problems.append(
                f"{_source(a, node)} and {_source(b, node)} overlap in {len(shared)} "
                f"{'node' if len(shared) == 1 else 'nodes'} of the mesh made from {surface.path.name}, e.g. node "
                f"{node} at {where}: node sets must not share nodes"
            )
    return problems


def _source(node_set: NodeSet, node: int) -> str:
    """The selection of a node set that selected `node`."""
    return next(option for option, nodes in node_set.sources if node in nodes)
