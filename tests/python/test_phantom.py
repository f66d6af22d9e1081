"""The committed phantom meshes are exactly what the generator makes, and the renderer draws them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import generate
import render

HERE = Path(generate.__file__).resolve().parent


def test_coarse_mesh_regenerates_byte_for_byte(tmp_path: Path) -> None:
    # In a fresh interpreter, as a user runs the generator: after the other tests of this process have
    # run with ORT_DYLIB_PATH set (as scripts/test sets it), gmsh in this process writes a mesh that
    # differs in a few digits, so process-wide state (floating-point mode, likely) leaks into it.
    script = (
        f"import generate; from pathlib import Path; print(generate.build(generate.COARSE, Path({str(tmp_path)!r})))"
    )
    result = subprocess.run([sys.executable, "-c", script], cwd=HERE, capture_output=True, text=True, check=True)
    out = Path(result.stdout.strip().splitlines()[-1])
    assert out.read_bytes() == (HERE / "liver-coarse.msh").read_bytes()


def test_boundary_is_labelled_and_rendered(tmp_path: Path) -> None:
    nodes, tets, regions, node_sets = render.read_mesh(HERE / "liver-coarse.msh")
    assert set(regions) == {"liver", "gallbladder", "ducts"}
    assert {f"grasp_{i:02d}" for i in range(1, 11)} | {"fixed"} <= set(node_sets)
    tris, _ = render.boundary(tets, regions)
    # Every boundary edge is shared by exactly two boundary triangles.
    edges: dict[tuple[int, int], int] = {}
    for a, b, c in tris:
        for e in ((a, b), (b, c), (c, a)):
            key = (min(e), max(e))
            edges[key] = edges.get(key, 0) + 1
    assert set(edges.values()) == {2}
    png = tmp_path / "coarse.png"
    render.render(HERE / "liver-coarse.msh", png)
    assert png.stat().st_size > 10_000
