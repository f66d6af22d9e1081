"""nak_organ: a closed surface in, a labelled tetrahedral mesh and model.toml that nak accepts out, and
every refusal naming the file, what is wrong and where.

The tests write their own surfaces (an ellipsoid as binary and ASCII STL in mm, a two-lobed shape as OBJ
with groups, an ellipsoid as binary PLY with a vertex label) and mesh them coarsely (TARGET nodes).
`nak mesh info` validates every output when the binary is there (NAK_BIN, default target/debug/nak).
"""

from __future__ import annotations

import math
import os
import shutil
import struct
import subprocess
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

import meshio
import numpy as np
import pytest
from numpy.typing import NDArray

from conftest import ROOT
from nak_organ.cli import main
from nak_organ.errors import OrganInputError
from nak_organ.graphs import connected_components, vertex_neighbours
from nak_organ.intersections import intersecting_pairs
from nak_organ.meshing import VolumeMesh, boundary_triangles
from nak_organ.model_toml import PHANTOM_DIAGONAL_M
from nak_organ.msh import write_msh
from nak_organ.placing import REFUSED, nak_reason, place, staging_folder
from nak_organ.selections import NodeSet

Floats = NDArray[np.float64]
Ints = NDArray[np.int64]

TARGET = 1500
SEMI_AXES_MM = (80.0, 60.0, 50.0)
# The automatic grasp regions' largest area over their smallest: balancing aims at 1.2 (regions.py);
# joining stray pieces afterwards may move it a little.
AREA_RATIO_BOUND = 1.35
# Where the ellipsoid is fixed: a sphere around its -x end (mm).
ELLIPSOID_FIXED = "sphere:-80,0,0,20"


# --- Surfaces the tests write --------------------------------------------------------------------------


def icosphere(subdivisions: int) -> tuple[Floats, Ints]:
    """A unit sphere: an icosahedron whose faces are split in four `subdivisions` times (20 × 4^n faces),
    counter-clockwise seen from outside."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    corners = [(-1.0, t, 0.0), (1.0, t, 0.0), (-1.0, -t, 0.0), (1.0, -t, 0.0), (0.0, -1.0, t), (0.0, 1.0, t)]
    corners += [(0.0, -1.0, -t), (0.0, 1.0, -t), (t, 0.0, -1.0), (t, 0.0, 1.0), (-t, 0.0, -1.0), (-t, 0.0, 1.0)]
    points = [np.array(c, dtype=float) / np.linalg.norm(c) for c in corners]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2)]
    faces += [(10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5)]
    faces += [(2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    for _ in range(subdivisions):
        middle: dict[tuple[int, int], int] = {}

        def mid(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in middle:
                m = points[a] + points[b]
                points.append(m / np.linalg.norm(m))
                middle[key] = len(points) - 1
            return middle[key]

        split = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            split += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = split
    return np.array(points), np.array(faces, dtype=np.int64)


def ellipsoid(subdivisions: int = 4) -> tuple[Floats, Ints]:
    """The test organ: semi-axes 80 × 60 × 50 mm (1005 mL), 5,120 faces by default."""
    unit, faces = icosphere(subdivisions)
    # Through float32 so that binary and ASCII STL hold the same numbers.
    return (unit * np.array(SEMI_AXES_MM)).astype(np.float32).astype(np.float64), faces


def two_lobes() -> tuple[Floats, Ints]:
    """A peanut 168 mm long: two lobes joined by a waist (radius 0.5 at the middle, 1.2 at the ends)."""
    unit, faces = icosphere(4)
    radius = 0.5 + 0.7 * np.abs(unit[:, 0]) ** 1.5
    return unit * radius[:, None] * np.array([70.0, 45.0, 40.0]), faces


def write_stl_binary(path: Path, vertices: Floats, faces: Ints) -> Path:
    with path.open("wb") as out:
        out.write(b"binary STL written by test_organ".ljust(80))
        out.write(struct.pack("<I", len(faces)))
        for face in faces:
            out.write(struct.pack("<3f", 0.0, 0.0, 0.0))
            out.write(vertices[face].astype("<f4").tobytes())
            out.write(b"\0\0")
    return path


def write_stl_ascii(path: Path, vertices: Floats, faces: Ints) -> Path:
    lines = ["solid test"]
    for face in faces:
        lines += ["facet normal 0 0 0", " outer loop"]
        lines += [f"  vertex {x!r} {y!r} {z!r}" for x, y, z in vertices[face].tolist()]
        lines += [" endloop", "endfacet"]
    path.write_text("\n".join([*lines, "endsolid test", ""]))
    return path


def write_obj(path: Path, vertices: Floats, faces: Ints, groups: list[str]) -> Path:
    """OBJ with each face under its group's `g` statement."""
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in vertices.tolist()]
    for name in sorted(set(groups)):
        lines.append(f"g {name}")
        lines += [f"f {a + 1} {b + 1} {c + 1}" for (a, b, c), g in zip(faces.tolist(), groups) if g == name]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_ply_binary(path: Path, vertices: Floats, faces: Ints, labels: Ints) -> Path:
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by test_organ\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\nproperty int label\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    record = np.dtype([("xyz", "<f4", 3), ("label", "<i4")])
    vertex_data = np.zeros(len(vertices), dtype=record)
    vertex_data["xyz"], vertex_data["label"] = vertices, labels
    face_data = np.zeros(len(faces), dtype=[("n", "u1"), ("v", "<i4", 3)])
    face_data["n"], face_data["v"] = 3, faces
    path.write_bytes(header.encode() + vertex_data.tobytes() + face_data.tobytes())
    return path


# --- Running and reading back ---------------------------------------------------------------------------


def mesh_command(surface: Path, out: Path, *options: str) -> list[str]:
    return ["mesh", str(surface), "--units", "mm", "--out", str(out), "--target-nodes", str(TARGET), *options]


def run_in_subprocess(arguments: list[str]) -> subprocess.CompletedProcess[str]:
    """As a user runs it. Also keeps gmsh away from this process's state (see test_phantom.py)."""
    environment = {**os.environ, "PYTHONPATH": str(ROOT / "organ")}
    command = [sys.executable, "-m", "nak_organ", *arguments]
    return subprocess.run(command, capture_output=True, text=True, env=environment, check=False)


def refusal(arguments: list[str], capsys: pytest.CaptureFixture[str]) -> list[str]:
    """The problem lines of a run that must be refused (exit status 2)."""
    assert main(arguments) == 2
    lines = capsys.readouterr().err.strip().split("\n")
    assert all(line.startswith("error: ") for line in lines), lines
    return lines


@dataclass
class Written:
    points: Floats
    tets: Ints
    node_sets: dict[str, Ints]

    def boundary(self) -> Ints:
        """Boundary triangles: faces of one tetrahedron only."""
        faces = self.tets[:, [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]].reshape(-1, 3)
        _, first, counts = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True)
        boundary: Ints = faces[first[counts == 1]]
        return boundary


def read_written(directory: Path) -> Written:
    """organ.msh as meshio (an independent reader) sees it: node sets from the point physical groups."""
    mesh = meshio.read(directory / "organ.msh")
    tets = np.concatenate([c.data for c in mesh.cells if c.type == "tetra"]).astype(np.int64)
    names = {int(tag): name for name, (tag, dim) in mesh.field_data.items() if dim == 0}
    sets: dict[str, list[Ints]] = {}
    for cells, physical in zip(mesh.cells, mesh.cell_data["gmsh:physical"]):
        if cells.type == "vertex":
            sets.setdefault(names[int(physical[0])], []).append(cells.data.ravel().astype(np.int64))
    node_sets = {name: np.unique(np.concatenate(parts)) for name, parts in sets.items()}
    return Written(np.asarray(mesh.points, dtype=np.float64), tets, node_sets)


def tet_volume(points: Floats, tets: Ints) -> float:
    a, b, c, d = (points[tets[:, k]] for k in range(4))
    return float(np.sum(np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a)) / 6.0)


@pytest.fixture(scope="module")
def nak() -> Path:
    path = Path(os.environ.get("NAK_BIN", ROOT / "target" / "debug" / "nak")).resolve()
    if not path.exists():
        pytest.skip(f"{path} not found: nak's own validation of the outputs is skipped (NAK_BIN names it)")
    return path


def nak_accepts(nak: Path, directory: Path) -> str:
    result = subprocess.run([str(nak), "mesh", "info", str(directory)], capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stderr
    return result.stdout


# --- The meshes the tests share -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def surfaces(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("surfaces")
    vertices, faces = ellipsoid()
    write_stl_binary(folder / "ellipsoid.stl", vertices, faces)
    write_stl_ascii(folder / "ellipsoid-ascii.stl", vertices, faces)
    lobes, lobe_faces = two_lobes()
    centres = lobes[lobe_faces].mean(axis=1)
    bare = (np.abs(centres[:, 0]) < 12.0) & (centres[:, 1] > 0.0)
    tip = centres[:, 0] > 0.85 * lobes[:, 0].max()
    groups = np.where(bare, "bare", np.where(tip, "tip", "skin")).tolist()
    write_obj(folder / "two-lobes.obj", lobes, lobe_faces, groups)
    labels = np.where(vertices[:, 0] < -60.0, 1, np.where(vertices[:, 0] > 60.0, 2, 0)).astype(np.int64)
    write_ply_binary(folder / "labelled.ply", vertices, faces, labels)
    return folder


@pytest.fixture(scope="module")
def ellipsoid_out(surfaces: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The binary STL ellipsoid, fixed at its -x end, with ten automatic grasp regions."""
    out = tmp_path_factory.mktemp("ellipsoid")
    result = run_in_subprocess(mesh_command(surfaces / "ellipsoid.stl", out, "--fixed", ELLIPSOID_FIXED))
    assert result.returncode == 0, result.stderr
    return out


@pytest.fixture(scope="module")
def lobes_out(surfaces: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The OBJ: fixed by its group `bare`, grasped at its group `tip` and by a box on the other lobe."""
    out = tmp_path_factory.mktemp("lobes")
    grasps = ["--grasp", "tip=group:tip", "--grasp", "left=box:-90,-50,-50,-70,50,50"]
    assert main(mesh_command(surfaces / "two-lobes.obj", out, "--fixed", "group:bare", *grasps)) == 0
    return out


@pytest.fixture(scope="module")
def ply_out(surfaces: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The PLY, fixed where label = 1, grasped where label = 2, written as binary MSH."""
    out = tmp_path_factory.mktemp("ply")
    options = ["--fixed", "group:1", "--grasp", "end=group:2", "--binary", "--name", "labelled kidney"]
    assert main(mesh_command(surfaces / "labelled.ply", out, *options)) == 0
    return out


# --- What is written ------------------------------------------------------------------------------------


def test_nak_accepts_every_output(nak: Path, ellipsoid_out: Path, lobes_out: Path, ply_out: Path) -> None:
    info = nak_accepts(nak, ellipsoid_out)
    assert "closed and manifold" in info and "grasp_10" in info
    assert "left" in nak_accepts(nak, lobes_out)
    assert "labelled kidney" in nak_accepts(nak, ply_out)


def test_the_ellipsoid_has_its_volume_and_about_the_target_node_count(ellipsoid_out: Path) -> None:
    mesh = read_written(ellipsoid_out)
    analytic = 4.0 / 3.0 * math.pi * math.prod(SEMI_AXES_MM) * 1e-9
    assert tet_volume(mesh.points, mesh.tets) == pytest.approx(analytic, rel=0.03)
    assert abs(len(mesh.points) / TARGET - 1.0) <= 0.25
    # Metres: the 160 mm axis.
    assert np.ptp(mesh.points[:, 0]) == pytest.approx(0.160, abs=0.002)


def test_binary_and_ascii_stl_make_the_same_mesh(surfaces: Path, ellipsoid_out: Path, tmp_path: Path) -> None:
    result = run_in_subprocess(mesh_command(surfaces / "ellipsoid-ascii.stl", tmp_path, "--fixed", ELLIPSOID_FIXED))
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "organ.msh").read_bytes() == (ellipsoid_out / "organ.msh").read_bytes()


def test_the_same_input_gives_the_same_files(surfaces: Path, ellipsoid_out: Path, tmp_path: Path) -> None:
    result = run_in_subprocess(mesh_command(surfaces / "ellipsoid.stl", tmp_path, "--fixed", ELLIPSOID_FIXED))
    assert result.returncode == 0, result.stderr
    for name in ("organ.msh", "model.toml"):
        assert (tmp_path / name).read_bytes() == (ellipsoid_out / name).read_bytes(), name
    # The summary reports what the tests check.
    assert "tetrahedra" in result.stdout and "radius ratio" in result.stdout and "grasp_10" in result.stdout


def test_automatic_grasp_regions_cover_the_free_surface_in_similar_areas(ellipsoid_out: Path) -> None:
    mesh = read_written(ellipsoid_out)
    triangles = mesh.boundary()
    a, b, c = (mesh.points[triangles[:, k]] for k in range(3))
    area = np.bincount(triangles.ravel(), weights=np.repeat(np.linalg.norm(np.cross(b - a, c - a), axis=1) / 6.0, 3))
    fixed = mesh.node_sets["fixed"]
    assert np.allclose(mesh.points[fixed] * 1000, [-80, 0, 0], atol=20.0)
    # Free: on the boundary, not fixed, sharing no boundary triangle with a fixed node.
    touches_fixed = np.any(np.isin(triangles, fixed), axis=1)
    free = np.setdiff1d(np.unique(triangles), np.unique(triangles[touches_fixed]))
    regions = [mesh.node_sets[f"grasp_{i:02d}"] for i in range(1, 11)]
    assert set(mesh.node_sets) == {"fixed"} | {f"grasp_{i:02d}" for i in range(1, 11)}
    together = np.concatenate(regions)
    assert len(together) == len(np.unique(together)), "regions overlap"
    assert np.array_equal(np.sort(together), free), "regions do not cover exactly the free surface"
    areas = [area[r].sum() for r in regions]
    assert max(areas) / min(areas) <= AREA_RATIO_BOUND, areas
    u, v = vertex_neighbours(triangles)
    for region in regions:
        inside = np.isin(u, region) & np.isin(v, region)
        pieces = connected_components(len(mesh.points), u[inside], v[inside])
        assert len(np.unique(pieces[region])) == 1, "a region falls apart"


def test_model_toml_is_the_phantoms_with_one_region_and_equal_weights(ellipsoid_out: Path) -> None:
    ours = tomllib.loads((ellipsoid_out / "model.toml").read_text())
    phantom = tomllib.loads((ROOT / "models" / "phantom-liver" / "model.toml").read_text())
    assert ours["mesh"] == {"name": "ellipsoid", "default": "organ.msh", "units": "m"}
    for table in ("prior", "body", "hyperelastic"):
        assert ours[table] == phantom[table], table
    assert ours["regions"] == {"organ": phantom["regions"]["liver"]}
    sampling = ours["sampling"]
    assert (sampling["neighbours_min"], sampling["neighbours_max"]) == (3, 7)
    assert [r["node_set"] for r in sampling["grasp_regions"]] == [f"grasp_{i:02d}" for i in range(1, 11)]
    assert sum(r["weight"] for r in sampling["grasp_regions"]) == pytest.approx(1.0, abs=1e-12)
    assert {r["weight"] for r in sampling["grasp_regions"]} == {0.1}
    scale = np.linalg.norm(np.ptp(read_written(ellipsoid_out).points, axis=0)) / PHANTOM_DIAGONAL_M
    expected = np.array(phantom["sampling"]["displacement_min_mm"]) * scale
    assert np.allclose(sampling["displacement_min_mm"], expected, atol=0.051)


def test_the_phantom_diagonal_is_the_phantom_meshs() -> None:
    points = meshio.read(ROOT / "models" / "phantom-liver" / "liver.msh").points
    assert np.linalg.norm(np.ptp(points, axis=0)) == pytest.approx(PHANTOM_DIAGONAL_M, abs=5e-5)


def test_obj_groups_and_boxes_select_their_nodes(lobes_out: Path) -> None:
    mesh = read_written(lobes_out)
    assert set(mesh.node_sets) == {"fixed", "tip", "left"}
    fixed, tip, left = (mesh.points[mesh.node_sets[n]] * 1000 for n in ("fixed", "tip", "left"))
    assert np.all(np.abs(fixed[:, 0]) < 16.0) and np.all(fixed[:, 1] > -2.0)
    assert np.all(tip[:, 0] > 0.8 * 84.0)
    assert np.all(left[:, 0] <= -70.0 + 1e-9)
    model = tomllib.loads((lobes_out / "model.toml").read_text())
    assert [(r["node_set"], r["weight"]) for r in model["sampling"]["grasp_regions"]] == [("tip", 0.5), ("left", 0.5)]
    assert model["sampling"]["displacement_max_mm"] != [50.0, 50.0, 90.0], "the cuboid is scaled"


def test_ply_labels_select_their_nodes_and_binary_msh_is_written(ply_out: Path) -> None:
    assert (ply_out / "organ.msh").read_bytes().startswith(b"$MeshFormat\n4.1 1 8\n")
    mesh = read_written(ply_out)
    fixed, end = (mesh.points[mesh.node_sets[n]] * 1000 for n in ("fixed", "end"))
    assert np.all(fixed[:, 0] < -55.0) and np.all(end[:, 0] > 55.0)
    assert tomllib.loads((ply_out / "model.toml").read_text())["mesh"]["name"] == "labelled kidney"


def test_displacements_can_be_given(surfaces: Path, tmp_path: Path) -> None:
    options = ["--fixed", ELLIPSOID_FIXED, "--grasp-regions", "3"]
    options += ["--displacement-min-mm=-10,-10,-5", "--displacement-max-mm=5,5,10"]
    assert main(mesh_command(surfaces / "ellipsoid.stl", tmp_path, *options)) == 0
    sampling = tomllib.loads((tmp_path / "model.toml").read_text())["sampling"]
    assert sampling["displacement_min_mm"] == [-10.0, -10.0, -5.0]
    assert len(sampling["grasp_regions"]) == 3
    assert sum(r["weight"] for r in sampling["grasp_regions"]) == pytest.approx(1.0, abs=1e-12)


def test_files_are_placed_once_nak_accepts_them(
    nak: Path, surfaces: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "checked"
    (out / REFUSED).mkdir(parents=True)  # left by an earlier refused run: gone once a mesh is accepted
    options = ["--fixed", ELLIPSOID_FIXED, "--target-nodes", "500", "--grasp-regions", "2", "--nak", str(nak)]
    assert main(mesh_command(surfaces / "ellipsoid.stl", out, *options)) == 0
    assert f"checked     nak mesh info accepts the mesh and its configuration ({nak})" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["model.toml", "organ.msh"]
    # Without a nak binary the files are placed, and the summary says they are unchecked.
    missing = tmp_path / "no-such-nak"
    options = [*options[:-1], str(missing)]
    assert main(mesh_command(surfaces / "ellipsoid.stl", tmp_path / "unchecked", *options)) == 0
    assert f"checked     not by nak mesh info: no nak binary at {missing}" in capsys.readouterr().out
    assert sorted(p.name for p in (tmp_path / "unchecked").iterdir()) == ["model.toml", "organ.msh"]


# --- Refusals -------------------------------------------------------------------------------------------


def test_an_open_surface_is_refused_naming_an_edge(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    vertices, faces = ellipsoid(3)
    path = write_stl_binary(tmp_path / "open.stl", vertices, faces[1:])
    [line] = refusal(mesh_command(path, tmp_path / "out", "--fixed", ELLIPSOID_FIXED), capsys)
    assert f"{path}: the surface is open: 3 edges belong to one face only, e.g. the edge from vertex" in line
    assert " mm to vertex " in line and "(face " in line


def test_the_command_line_exits_2_without_a_traceback(tmp_path: Path) -> None:
    vertices, faces = ellipsoid(3)
    path = write_stl_binary(tmp_path / "open.stl", vertices, faces[1:])
    result = run_in_subprocess(mesh_command(path, tmp_path / "out", "--fixed", ELLIPSOID_FIXED))
    assert result.returncode == 2
    assert result.stderr.startswith("error: ") and "Traceback" not in result.stderr


def test_an_out_that_cannot_be_written_is_refused(
    surfaces: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    options = ["--fixed", ELLIPSOID_FIXED, "--target-nodes", "300", "--grasp-regions", "1"]
    [line] = refusal(mesh_command(surfaces / "ellipsoid.stl", a_file, *options), capsys)
    assert line == f"error: --out {a_file}: cannot write there: it is a file, not a directory"
    # Inside a file: found when the folder is made, after meshing.
    [line] = refusal(mesh_command(surfaces / "ellipsoid.stl", a_file / "organ", *options), capsys)
    assert line == f"error: --out {a_file / 'organ'}: cannot write there: Not a directory"


def test_non_manifold_surfaces_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    vertices, faces = ellipsoid(3)
    # A face used twice: its edges have three faces each.
    path = write_obj(tmp_path / "crowded.obj", vertices, np.r_[faces, faces[:1]], ["skin"] * (len(faces) + 1))
    lines = refusal(mesh_command(path, tmp_path / "out", "--fixed", ELLIPSOID_FIXED), capsys)
    assert any("3 edges are shared by more than two faces, e.g. the edge from vertex" in line for line in lines)
    assert any(f"(faces 0, {len(faces)}" in line or "faces 0, " in line for line in lines)
    # Two ellipsoids touching at one vertex: a pinched vertex, and two shells.
    tip = int(np.argmax(vertices[:, 0]))
    other = vertices - vertices[int(np.argmin(vertices[:, 0]))] + vertices[tip]
    index = np.arange(len(vertices)) + len(vertices)
    index[int(np.argmin(vertices[:, 0]))] = tip
    pinched = write_obj(tmp_path / "pinched.obj", np.r_[vertices, other], np.r_[faces, index[faces]], ["a"] * 2560)
    lines = refusal(mesh_command(pinched, tmp_path / "out", "--fixed", ELLIPSOID_FIXED), capsys)
    assert any(
        f"1 vertex joins separate fans of faces (the surface touches itself there), e.g. vertex {tip}" in line
        for line in lines
    ), lines
    assert any(
        "the surface has 2 separate shells (1280 faces with face 0, 1280 faces with face 1280)" in line
        for line in lines
    ), lines


def test_inconsistent_orientation_and_degenerate_faces_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    vertices, faces = ellipsoid(3)
    flipped = faces.copy()
    flipped[7] = flipped[7][::-1]
    path = write_obj(tmp_path / "flipped.obj", vertices, flipped, ["skin"] * len(faces))
    [line] = refusal(mesh_command(path, tmp_path / "out", "--fixed", ELLIPSOID_FIXED), capsys)
    assert "not consistently oriented: 3 edges are traversed in the same direction by both their faces" in line
    assert "faces 7, " in line or ", 7)" in line
    collapsed = faces.copy()
    collapsed[4, 1] = collapsed[4, 0]
    path = write_obj(tmp_path / "collapsed.obj", vertices, collapsed, ["skin"] * len(faces))
    [line] = refusal(mesh_command(path, tmp_path / "out", "--fixed", ELLIPSOID_FIXED), capsys)
    assert "1 degenerate face (no area: a repeated or collinear vertex), e.g. face 4 with vertex" in line


def test_a_self_intersecting_surface_is_refused_naming_two_faces(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    vertices, faces = ellipsoid(3)
    # The top pole pushed out through the bottom: its fan of faces crosses the far side.
    top = int(np.argmax(vertices[:, 2]))
    vertices[top, 2] = -70.0
    path = write_obj(tmp_path / "pierced.obj", vertices, faces, ["skin"] * len(faces))
    [line] = refusal(mesh_command(path, tmp_path / "out", "--fixed", ELLIPSOID_FIXED), capsys)
    assert "the surface intersects itself: " in line and " pairs of faces cross, e.g. faces " in line
    first, second = (int(w) for w in line.split("e.g. faces ")[1].split(" near")[0].split(" and "))
    assert top in faces[first] or top in faces[second]


def test_units_that_contradict_the_size_are_refused_both_ways(
    surfaces: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fixed = ["--fixed", ELLIPSOID_FIXED]
    arguments = mesh_command(surfaces / "ellipsoid.stl", tmp_path, *fixed)
    [line] = refusal([*arguments, "--units", "m"], capsys)
    assert "with --units m the surface is 224 m across (bounding-box diagonal), too large for an organ" in line
    assert "pass --units mm (which makes it 22.4 cm)" in line
    vertices, faces = ellipsoid(3)
    in_metres = write_stl_binary(tmp_path / "metres.stl", vertices / 1000.0, faces)
    [line] = refusal(mesh_command(in_metres, tmp_path, *fixed), capsys)
    assert "with --units mm the surface is 0.224 mm across (bounding-box diagonal), too small for an organ" in line
    assert "pass --units m (which makes it 22.4 cm)" in line
    # 22.4 units across: as mm or as cm an organ, as m not.
    in_cm = write_stl_binary(tmp_path / "either.stl", vertices / 10.0, faces)
    [line] = refusal([*mesh_command(in_cm, tmp_path, *fixed), "--units", "m"], capsys)
    assert line.endswith("the coordinates look like mm or cm: pass --units mm (which makes it 2.24 cm)"), line


def test_selections_are_refused_before_meshing(
    surfaces: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    stl, obj = surfaces / "ellipsoid.stl", surfaces / "two-lobes.obj"
    [line] = refusal(mesh_command(stl, tmp_path), capsys)
    assert line.startswith(f"error: {stl}: nothing is fixed: give --fixed SPEC")
    [line] = refusal(mesh_command(obj, tmp_path, "--fixed", "group:liver"), capsys)
    assert line == "error: --fixed group:liver: two-lobes.obj has no group 'liver'; its groups: bare, skin, tip"
    [line] = refusal(mesh_command(stl, tmp_path, "--fixed", "vertices:1,99999"), capsys)
    assert line.endswith(
        "vertices:1,99999: ellipsoid.stl has no vertex 99999 on a face (vertex ids run from 0 to 2561)"
    )
    [line] = refusal(mesh_command(stl, tmp_path, "--fixed", "sphere:1,2,3"), capsys)
    assert line == "error: --fixed sphere:1,2,3: a sphere takes 4 numbers, not 3"
    [line] = refusal(mesh_command(stl, tmp_path, "--fixed", ELLIPSOID_FIXED, "--grasp", "fixed=group:a"), capsys)
    assert "--grasp fixed=group:a: expected NAME=SPEC" in line


def test_empty_and_overlapping_selections_are_refused_together(
    surfaces: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    options = ["--fixed", ELLIPSOID_FIXED, "--fixed", "sphere:0,0,500,10"]
    options += ["--grasp", "a=sphere:80,0,0,20", "--grasp", "b=box:60,-60,-60,100,60,60"]
    options += ["--grasp", "c=sphere:-70,0,0,15"]
    lines = refusal(mesh_command(surfaces / "ellipsoid.stl", tmp_path, *options), capsys)
    assert len(lines) == 3, lines
    assert lines[0].startswith(
        "error: --fixed sphere:0,0,500,10 selects no boundary node of the mesh made from ellipsoid.stl; the nearest"
    )
    assert "mm from its centre" in lines[0]
    assert lines[1].startswith(f"error: --fixed {ELLIPSOID_FIXED} and --grasp c=sphere:-70,0,0,15 overlap in ")
    assert lines[2].startswith("error: --grasp a=sphere:80,0,0,20 and --grasp b=box:60,-60,-60,100,60,60 overlap in ")
    for line in lines[1:]:
        assert " of the mesh made from ellipsoid.stl, e.g. node " in line
        assert " mm: node sets must not share nodes" in line


def test_a_mesh_nak_refuses_is_not_placed(nak: Path, ellipsoid_out: Path, tmp_path: Path) -> None:
    """nak's loader has the last word: the ellipsoid's mesh with one tetrahedron turned inside out (which
    gmsh does not make, hence written here) stays out of DIR, and nak's reason is the refusal."""
    written = read_written(ellipsoid_out)
    tets = written.tets.copy()
    tets[7, [0, 1]] = tets[7, [1, 0]]
    out = tmp_path / "organ"
    out.mkdir()
    (out / "organ.msh").write_text("an earlier mesh")
    staging = staging_folder(out)
    mesh = VolumeMesh(written.points, tets, boundary_triangles(tets), 0.0, ())
    write_msh(staging / "organ.msh", mesh, [NodeSet(n, v, ()) for n, v in written.node_sets.items()], False)
    shutil.copy(ellipsoid_out / "model.toml", staging / "model.toml")
    with pytest.raises(OrganInputError) as refused:
        place(staging, out, nak)
    [line] = refused.value.problems
    kept = out / REFUSED
    assert line.startswith(
        f"nak mesh info refuses the written mesh ({out} is unchanged; see {kept}): {kept / 'organ.msh'}: "
        "1 inverted tetrahedra (volume < 0), e.g. element "
    ), line
    assert (out / "organ.msh").read_text() == "an earlier mesh"
    assert sorted(p.name for p in out.iterdir()) == ["organ.msh", REFUSED]
    assert sorted(p.name for p in kept.iterdir()) == ["model.toml", "organ.msh"]


def test_nak_reason_is_the_innermost_cause() -> None:
    report = "Error: cannot load mesh d\n\nCaused by:\n    0: reading d\n    1: d/organ.msh: node 3: bad\n\n"
    assert nak_reason(report + "Stack backtrace:\n   0: main\n") == "d/organ.msh: node 3: bad"
    assert nak_reason("Error: cannot load mesh d\n\nCaused by:\n    d/model.toml: no [mesh]\n") == (
        "d/model.toml: no [mesh]"
    )
    assert nak_reason("Error: no such command\n") == "no such command"


# --- The geometry underneath ----------------------------------------------------------------------------


def test_intersecting_pairs_by_shared_vertices() -> None:
    # Two triangles crossing like links of a chain, sharing nothing.
    crossing = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0.5, 0.5, -1], [0.5, 0.5, 1], [3, 3, 0]], dtype=float)
    assert intersecting_pairs(crossing, np.array([[0, 1, 2], [3, 4, 5]])).tolist() == [[0, 1]]
    # Sharing vertex 0: apart (a fan), then folded through each other.
    fan = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0.1], [0, -1, 0.1]], dtype=float)
    assert len(intersecting_pairs(fan, np.array([[0, 1, 2], [0, 3, 4]]))) == 0
    pierced = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.3, -1], [0.3, 0.3, 1]], dtype=float)
    assert intersecting_pairs(pierced, np.array([[0, 1, 2], [0, 3, 4]])).tolist() == [[0, 1]]
    # Sharing an edge: a hinge is fine, folded flat onto each other is not.
    hinge = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0.5]], dtype=float)
    assert len(intersecting_pairs(hinge, np.array([[0, 1, 2], [1, 0, 3]]))) == 0
    folded = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.5, 0.5, 0]], dtype=float)
    assert intersecting_pairs(folded, np.array([[0, 1, 2], [1, 0, 3]])).tolist() == [[0, 1]]
