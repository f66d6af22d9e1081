"""nak's VTK files against an independent implementation (meshio): what nak writes, meshio reads
with the same geometry and data; what meshio writes (binary, zlib-compressed, as VTK's own writers
do), nak reads as the same mesh."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import meshio
import numpy as np
import pytest

from conftest import ROOT

PHANTOM = ROOT / "models" / "phantom-liver"


def nak(binary: Path, *args: str | Path) -> str:
    done = subprocess.run([str(binary), *map(str, args)], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    return done.stdout


@pytest.fixture()
def workdir(tmp_path: Path) -> Path:
    shutil.copy(PHANTOM / "model.toml", tmp_path / "model.toml")
    return tmp_path


def info(binary: Path, mesh: Path) -> dict[str, str]:
    """`nak mesh info`'s lines by their first word (regions and node sets by name)."""
    lines = nak(binary, "mesh", "info", mesh).splitlines()
    return {line.split()[0]: line for line in lines if line.strip()}


def test_a_prediction_for_paraview_reads_in_meshio_as_the_deformed_phantom(nak_binary: Path, workdir: Path) -> None:
    grasps = workdir / "grasps.json"
    grasps.write_text(
        json.dumps({"grasps": [{"point": [0.0, -0.02, 0.05], "radius": 0.01, "displacement": [0.0, 0.02, 0.0]}]})
    )
    nak(nak_binary, "predict", "--mesh", PHANTOM / "liver-coarse.msh", "--grasps", grasps, "--out", workdir / "u.npy")
    nak(nak_binary, "predict", "--mesh", PHANTOM / "liver-coarse.msh", "--grasps", grasps, "--out", workdir / "u.vtu")
    nak(nak_binary, "mesh", "convert", PHANTOM / "liver-coarse.msh", workdir / "rest.vtu")
    u = np.load(workdir / "u.npy")
    deformed = meshio.read(workdir / "u.vtu")
    rest = meshio.read(workdir / "rest.vtu")
    assert [c.type for c in deformed.cells] == ["tetra"]
    np.testing.assert_array_equal(deformed.cells[0].data, rest.cells[0].data)
    np.testing.assert_array_equal(deformed.point_data["displacement"], u)
    np.testing.assert_allclose(deformed.points - rest.points, u, atol=1e-9)
    assert np.abs(u).max() > 1e-3
    regions = deformed.cell_data["region"][0]
    assert set(np.unique(regions)) == {1, 2, 3}
    for name in ["fixed", *(f"grasp_{i:02}" for i in range(1, 11))]:
        assert deformed.point_data[name].sum() > 0, name


@pytest.mark.parametrize("binary", [True, False])
def test_a_grid_written_by_meshio_loads_as_the_same_mesh(nak_binary: Path, workdir: Path, binary: bool) -> None:
    # Legacy .vtk from meshio names its FIELD types in VTK 9's XML style (vtktypeint32), which the
    # legacy reader does not take; legacy files as VTK's own writer makes them are checked in tests/vtk.rs.
    nak(nak_binary, "mesh", "convert", PHANTOM / "liver-coarse.msh", workdir / "nak.vtu")
    grid = meshio.read(workdir / "nak.vtu")
    # meshio reads nak's UInt64 connectivity as floats; VTK's own writers use Int64 (vtkIdType).
    grid.cells = [meshio.CellBlock("tetra", grid.cells[0].data.astype(np.int64))]
    # As 3D Slicer's SegmentMesher names its region array, with 64-bit ids and 0/1 node-set flags.
    grid.cell_data = {"labels": [grid.cell_data["region"][0].astype(np.int64)]}
    grid.point_data = {k: v.astype(np.int32) for k, v in grid.point_data.items()}
    meshio.write(workdir / "mesh.vtu", grid, binary=binary, compression="zlib" if binary else None)
    read, original = info(nak_binary, workdir / "mesh.vtu"), info(nak_binary, PHANTOM / "liver-coarse.msh")
    if binary:
        assert read["hash"] == original["hash"]
    # ASCII rounds coordinates in their last digits (so the hash differs); nothing else may.
    del read["mesh"], read["hash"], original["mesh"], original["hash"]
    assert read == original
