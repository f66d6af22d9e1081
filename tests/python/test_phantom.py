"""The committed phantom meshes are exactly what the generator makes, and the renderer draws them."""

from __future__ import annotations

from pathlib import Path

import generate
import render

HERE = Path(generate.__file__).resolve().parent


def test_coarse_mesh_regenerates_byte_for_byte(tmp_path: Path) -> None:
    out = generate.build(generate.COARSE, tmp_path)
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
