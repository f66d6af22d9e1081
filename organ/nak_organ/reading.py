"""Reading a closed triangle surface from STL (ASCII or binary), OBJ or PLY (ASCII or binary) into metres.

What each format keeps: OBJ's `g`/`o` statements label the faces after them (selectable as `group:NAME`);
a PLY's integer vertex property `label` (or its only integer vertex property) labels the vertices.
Coincident vertices are merged, exactly (bit for bit): STL repeats every corner, and OBJ files split
vertices at texture seams. Near-coincident vertices are not merged, since that would be a repair.

Vertex ids in messages and in `vertices:` selections are the file's own, 0-based, in file order (OBJ's
1-based index minus one); an STL has no vertex ids, so its vertices are numbered in order of first
appearance, as most viewers number them after merging. Face ids are the file's faces, 0-based; a
polygon split into a fan of triangles gives each triangle its id.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from .errors import OrganInputError

Floats = NDArray[np.float64]
Ints = NDArray[np.int64]

METRES_PER_UNIT = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}


@dataclass(frozen=True)
class Surface:
    """A triangle surface as read, in metres, with coincident vertices merged."""

    path: Path
    units: str
    vertices: Floats
    """(V, 3) positions in metres."""
    faces: Ints
    """(F, 3) vertex indices."""
    vertex_ids: Ints
    """Per vertex: the id the user knows it by (see the module's docstring)."""
    id_to_vertex: Ints
    """Per user vertex id: its vertex, or -1 when no face uses it."""
    face_ids: Ints
    """Per triangle: the file's face index."""
    face_groups: Ints
    """Per triangle: an index into `group_names`, or -1 before any `g`/`o` statement."""
    group_names: tuple[str, ...]
    vertex_labels: Ints | None
    """Per vertex: the PLY label property's value; None when the file has no such property."""
    label_property: str | None

    def in_units(self, points: Floats) -> Floats:
        """Positions in metres, back in the file's units."""
        return points / METRES_PER_UNIT[self.units]

    def point(self, position: Floats) -> str:
        """A position in metres, written in the file's units for messages."""
        x, y, z = self.in_units(position)
        return f"({x:.4g}, {y:.4g}, {z:.4g}) {self.units}"

    def vertex(self, index: int) -> str:
        """A vertex for messages: its id and position."""
        return f"vertex {self.vertex_ids[index]} at {self.point(self.vertices[index])}"


@dataclass
class _Raw:
    """What a parser finds, before merging: points in file units and triangles into them."""

    points: Floats
    triangles: Ints
    face_ids: Ints
    face_groups: Ints
    group_names: tuple[str, ...] = ()
    point_labels: Ints | None = None
    label_property: str | None = None
    points_have_ids: bool = True
    """False for STL, whose points are its faces' corners."""


def read_surface(path: Path, units: str) -> Surface:
    """Reads `path` (by its extension), scales it to metres and merges coincident vertices."""
    try:
        data = path.read_bytes()
    except OSError as e:
        raise OrganInputError([f"{path}: cannot read: {e.strerror}"]) from None
    suffix = path.suffix.lower()
    parsers = {".stl": _parse_stl, ".obj": _parse_obj, ".ply": _parse_ply}
    if suffix not in parsers:
        raise OrganInputError([f"{path}: unknown surface format {suffix!r}: nak_organ reads .stl, .obj and .ply"])
    raw = parsers[suffix](data, path)
    if len(raw.triangles) == 0:
        raise OrganInputError([f"{path}: the file holds no faces"])
    if not np.all(np.isfinite(raw.points)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(raw.points), axis=1))[0])
        raise OrganInputError([f"{path}: vertex {bad} has coordinates that are not finite numbers"])
    return _merge(raw, path, units)


def _merge(raw: _Raw, path: Path, units: str) -> Surface:
    used = np.zeros(len(raw.points), dtype=bool)
    used[raw.triangles.ravel()] = True
    # Bit-exact merging (adding 0.0 turns -0.0 into 0.0), in order of first appearance so that merged
    # ids follow the file.
    keys = np.ascontiguousarray(raw.points + 0.0).view(np.dtype((np.void, 24))).ravel()
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    used_unique = np.zeros(len(first), dtype=bool)
    used_unique[inverse[used]] = True
    kept = np.flatnonzero(used_unique)
    kept = kept[np.argsort(first[kept], kind="stable")]
    new_index = np.full(len(first), -1, dtype=np.int64)
    new_index[kept] = np.arange(len(kept))
    point_to_vertex = new_index[inverse]
    first_point = first[kept]
    if raw.points_have_ids:
        vertex_ids = first_point.astype(np.int64)
        id_to_vertex = np.where(used, point_to_vertex, -1)
    else:
        vertex_ids = np.arange(len(kept), dtype=np.int64)
        id_to_vertex = vertex_ids
    labels = None if raw.point_labels is None else raw.point_labels[first_point]
    return Surface(
        path=path,
        units=units,
        vertices=raw.points[first_point] * METRES_PER_UNIT[units],
        faces=point_to_vertex[raw.triangles],
        vertex_ids=vertex_ids,
        id_to_vertex=id_to_vertex,
        face_ids=raw.face_ids,
        face_groups=raw.face_groups,
        group_names=raw.group_names,
        vertex_labels=labels,
        label_property=raw.label_property,
    )


def _parse_stl(data: bytes, path: Path) -> _Raw:
    # A binary STL's size follows from its facet count; ASCII files start with "solid", but so do the
    # 80-byte headers of some binary writers, hence the size test first.
    if len(data) >= 84:
        (count,) = struct.unpack_from("<I", data, 80)
        if len(data) == 84 + 50 * count:
            record = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])
            facets = np.frombuffer(data, dtype=record, count=count, offset=84)
            points = facets["corners"].reshape(-1, 3).astype(np.float64)
            return _stl_raw(points)
    if not data.lstrip().startswith(b"solid"):
        raise OrganInputError(
            [f"{path}: neither an ASCII STL (no leading 'solid') nor a binary one (size is not 84 + 50 × facets)"]
        )
    return _stl_raw(_parse_ascii_stl(data.decode("ascii", errors="replace"), path))


def _stl_raw(points: Floats) -> _Raw:
    count = len(points) // 3
    return _Raw(
        points=points,
        triangles=np.arange(3 * count, dtype=np.int64).reshape(count, 3),
        face_ids=np.arange(count, dtype=np.int64),
        face_groups=np.full(count, -1, dtype=np.int64),
        points_have_ids=False,
    )


def _parse_ascii_stl(text: str, path: Path) -> Floats:
    corners: list[list[float]] = []
    facet_start = 0
    in_loop = False
    for number, line in enumerate(text.splitlines(), start=1):
        words = line.split()
        if not words:
            continue
        if words[0] == "outer":
            in_loop, facet_start = True, len(corners)
        elif words[0] == "vertex":
            if not in_loop or len(words) != 4:
                raise OrganInputError(
                    [f"{path}: line {number}: a vertex outside 'outer loop' or without 3 coordinates"]
                )
            try:
                corners.append([float(w) for w in words[1:]])
            except ValueError:
                raise OrganInputError([f"{path}: line {number}: {line.strip()!r} is not three numbers"]) from None
        elif words[0] == "endloop":
            if len(corners) - facet_start != 3:
                facet = facet_start // 3
                raise OrganInputError(
                    [f"{path}: line {number}: facet {facet} has {len(corners) - facet_start} vertices, not 3"]
                )
            in_loop = False
    return np.array(corners, dtype=np.float64).reshape(-1, 3)


def _parse_obj(data: bytes, path: Path) -> _Raw:
    points: list[list[float]] = []
    triangles: list[tuple[int, int, int]] = []
    face_ids: list[int] = []
    face_groups: list[int] = []
    groups: dict[str, int] = {}
    group = -1
    face_count = 0
    for number, line in enumerate(data.decode("utf-8", errors="replace").splitlines(), start=1):
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        where = f"{path}: line {number}"
        if words[0] == "v":
            try:
                points.append([float(w) for w in words[1:4]])
            except ValueError:
                raise OrganInputError([f"{where}: {line.strip()!r} is not a vertex 'v x y z'"]) from None
            if len(points[-1]) != 3:
                raise OrganInputError([f"{where}: a vertex needs three coordinates"])
        elif words[0] in ("g", "o"):
            name = " ".join(words[1:])
            group = groups.setdefault(name, len(groups)) if name else -1
        elif words[0] == "f":
            corners = [_obj_index(w, len(points), where) for w in words[1:]]
            if len(corners) < 3:
                raise OrganInputError([f"{where}: face {face_count} has {len(corners)} vertices"])
            # A polygon becomes a fan of triangles around its first corner: reading, not repairing.
            for k in range(1, len(corners) - 1):
                triangles.append((corners[0], corners[k], corners[k + 1]))
                face_ids.append(face_count)
                face_groups.append(group)
            face_count += 1
    return _Raw(
        points=np.array(points, dtype=np.float64).reshape(-1, 3),
        triangles=np.array(triangles, dtype=np.int64).reshape(-1, 3),
        face_ids=np.array(face_ids, dtype=np.int64),
        face_groups=np.array(face_groups, dtype=np.int64),
        group_names=tuple(groups),
    )


def _obj_index(word: str, count: int, where: str) -> int:
    """An OBJ face corner `v`, `v/vt`, `v//vn` or `v/vt/vn` as a 0-based vertex index."""
    try:
        index = int(word.split("/", 1)[0])
    except ValueError:
        raise OrganInputError([f"{where}: {word!r} is not a vertex index"]) from None
    resolved = index - 1 if index > 0 else count + index
    if index == 0 or not 0 <= resolved < count:
        raise OrganInputError([f"{where}: vertex index {index} is out of range (1 to {count} defined so far)"])
    return resolved


_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


@dataclass
class _PlyProperty:
    name: str
    type: str
    """numpy type code without byte order, e.g. "f4"."""
    count_type: str | None = None
    """For a list property: the type of its length."""


@dataclass
class _PlyElement:
    name: str
    count: int
    properties: list[_PlyProperty]


def _parse_ply(data: bytes, path: Path) -> _Raw:
    end = re.search(rb"end_header\r?\n", data)
    if not data.startswith(b"ply") or end is None:
        raise OrganInputError([f"{path}: not a PLY file (no 'ply' magic or no 'end_header')"])
    fmt, elements = _ply_header(data[: end.start()].decode("ascii", errors="replace"), path)
    body = data[end.end() :]
    if fmt == "ascii":
        values = _ply_ascii(body, elements, path)
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        values = _ply_binary(body, elements, "<" if fmt == "binary_little_endian" else ">", path)
    else:
        raise OrganInputError(
            [f"{path}: PLY format {fmt!r} is not one of ascii, binary_little_endian, binary_big_endian"]
        )
    vertex = values.get("vertex")
    faces = values.get("face")
    if vertex is None or faces is None:
        raise OrganInputError([f"{path}: a PLY surface needs 'vertex' and 'face' elements"])
    if not {"x", "y", "z"} <= vertex.keys():
        raise OrganInputError([f"{path}: the PLY vertex element has no x, y, z properties"])
    list_name = next((n for n in ("vertex_indices", "vertex_index") if n in faces), None)
    if list_name is None:
        raise OrganInputError([f"{path}: the PLY face element has no vertex_indices list"])
    points = np.column_stack([np.asarray(vertex[c], dtype=np.float64) for c in "xyz"])
    triangles, face_ids = _fan(faces[list_name], len(points), path)
    label_property = _ply_label_property(elements)
    labels = None if label_property is None else np.asarray(vertex[label_property], dtype=np.int64)
    return _Raw(
        points=points,
        triangles=triangles,
        face_ids=face_ids,
        face_groups=np.full(len(triangles), -1, dtype=np.int64),
        point_labels=labels,
        label_property=label_property,
    )


def _ply_header(header: str, path: Path) -> tuple[str, list[_PlyElement]]:
    fmt = ""
    elements: list[_PlyElement] = []
    for number, line in enumerate(header.splitlines(), start=1):
        words = line.split()
        bad = OrganInputError([f"{path}: header line {number}: cannot read {line.strip()!r}"])
        if not words or words[0] in ("ply", "comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) == 3:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append(_PlyElement(words[1], int(words[2]), []))
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in _PLY_TYPES:
            elements[-1].properties.append(_PlyProperty(words[2], _PLY_TYPES[words[1]]))
        elif (
            words[0] == "property"
            and elements
            and len(words) == 5
            and words[1] == "list"
            and words[2] in _PLY_TYPES
            and words[3] in _PLY_TYPES
        ):
            elements[-1].properties.append(_PlyProperty(words[4], _PLY_TYPES[words[3]], _PLY_TYPES[words[2]]))
        else:
            raise bad
    return fmt, elements


PlyValues = dict[str, dict[str, NDArray[np.generic] | list[list[int]]]]


def _ply_ascii(body: bytes, elements: list[_PlyElement], path: Path) -> PlyValues:
    lines = iter(body.decode("ascii", errors="replace").splitlines())
    values: PlyValues = {}
    for element in elements:
        columns: dict[str, list[float]] = {p.name: [] for p in element.properties if p.count_type is None}
        lists: dict[str, list[list[int]]] = {p.name: [] for p in element.properties if p.count_type is not None}
        for item in range(element.count):
            words = next(lines, "").split()
            at = 0
            try:
                for p in element.properties:
                    if p.count_type is None:
                        columns[p.name].append(float(words[at]))
                        at += 1
                    else:
                        n = int(words[at])
                        lists[p.name].append([int(w) for w in words[at + 1 : at + 1 + n]])
                        if len(lists[p.name][-1]) != n:
                            raise IndexError
                        at += 1 + n
            except (IndexError, ValueError):
                raise OrganInputError([f"{path}: {element.name} {item}: cannot read {' '.join(words)!r}"]) from None
        values[element.name] = {n: np.array(c) for n, c in columns.items()} | dict(lists.items())
    return values


def _ply_binary(body: bytes, elements: list[_PlyElement], order: str, path: Path) -> PlyValues:
    values: PlyValues = {}
    offset = 0
    for element in elements:
        fixed = _ply_fixed_dtype(body, offset, element, order)
        if fixed is not None and offset + fixed.itemsize * element.count <= len(body):
            records = np.frombuffer(body, dtype=fixed, count=element.count, offset=offset)
            # Records stay aligned up to the first list of another length, which this test sees.
            counts = [records[f"{p.name}__count"] for p in element.properties if p.count_type is not None]
            if all(np.all(c == c[0]) for c in counts if len(c)):
                values[element.name] = {
                    p.name: records[p.name] if p.count_type is None else records[p.name].astype(np.int64)
                    for p in element.properties
                }
                offset += fixed.itemsize * element.count
                continue
        values[element.name], offset = _ply_binary_items(body, offset, element, order, path)
    return values


def _ply_fixed_dtype(body: bytes, offset: int, element: _PlyElement, order: str) -> np.dtype[np.void] | None:
    """A record type for the element when every list has the length of the first item's (faces that are
    all triangles): then numpy reads the element at once."""
    fields: list[tuple[str, str] | tuple[str, str, tuple[int]]] = []
    at = offset
    for p in element.properties:
        if p.count_type is None:
            fields.append((p.name, order + p.type))
            at += np.dtype(p.type).itemsize
            continue
        size = np.dtype(p.count_type).itemsize
        if at + size > len(body):
            return None
        n = int(np.frombuffer(body, dtype=order + p.count_type, count=1, offset=at)[0])
        fields += [(f"{p.name}__count", order + p.count_type), (p.name, order + p.type, (n,))]
        at += size + n * np.dtype(p.type).itemsize
    return np.dtype(fields)


def _ply_binary_items(
    body: bytes, offset: int, element: _PlyElement, order: str, path: Path
) -> tuple[dict[str, NDArray[np.generic] | list[list[int]]], int]:
    """An element with lists of varying length (polygons), item by item."""
    columns: dict[str, list[float]] = {p.name: [] for p in element.properties if p.count_type is None}
    lists: dict[str, list[list[int]]] = {p.name: [] for p in element.properties if p.count_type is not None}
    try:
        for _ in range(element.count):
            for p in element.properties:
                if p.count_type is None:
                    columns[p.name].append(float(np.frombuffer(body, order + p.type, 1, offset)[0]))
                    offset += np.dtype(p.type).itemsize
                else:
                    n = int(np.frombuffer(body, order + p.count_type, 1, offset)[0])
                    offset += np.dtype(p.count_type).itemsize
                    lists[p.name].append(np.frombuffer(body, order + p.type, n, offset).tolist())
                    offset += n * np.dtype(p.type).itemsize
    except ValueError:
        raise OrganInputError([f"{path}: the binary body ends inside element {element.name!r}"]) from None
    return {n: np.array(c) for n, c in columns.items()} | dict(lists.items()), offset


def _fan(polygons: NDArray[np.generic] | list[list[int]], count: int, path: Path) -> tuple[Ints, Ints]:
    """Faces as triangles (polygons as fans around their first corner) and each triangle's face id."""
    if isinstance(polygons, np.ndarray) and polygons.ndim == 2 and polygons.shape[1] == 3:
        triangles = polygons.astype(np.int64)
        face_ids = np.arange(len(triangles), dtype=np.int64)
    else:
        fans = [(f, [p[0], p[k], p[k + 1]]) for f, p in enumerate(polygons) for k in range(1, len(p) - 1)]
        short = next((f for f, p in enumerate(polygons) if len(p) < 3), None)
        if short is not None:
            raise OrganInputError([f"{path}: face {short} has fewer than 3 vertices"])
        triangles = np.array([t for _, t in fans], dtype=np.int64).reshape(-1, 3)
        face_ids = np.array([f for f, _ in fans], dtype=np.int64)
    bad = np.flatnonzero(np.any((triangles < 0) | (triangles >= count), axis=1))
    if len(bad):
        raise OrganInputError([f"{path}: face {face_ids[bad[0]]} refers to a vertex outside 0 to {count - 1}"])
    return triangles, face_ids


def _ply_label_property(elements: list[_PlyElement]) -> str | None:
    """The vertex property that labels vertices: `label`, else the only integer one."""
    vertex = next((e for e in elements if e.name == "vertex"), None)
    if vertex is None:
        return None
    integers = [p.name for p in vertex.properties if p.count_type is None and p.type[0] in "iu"]
    if "label" in integers:
        return "label"
    return integers[0] if len(integers) == 1 else None
