"""Render a labelled tetrahedral mesh: boundary surface coloured by region, fixed area and grasp patches marked.

Usage: python models/phantom-liver/render.py liver.msh phantom-liver.png
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import gmsh
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

REGION_COLOURS = {"liver": "#a0522d", "gallbladder": "#4f9a4a", "ducts": "#d4b21f", "fascia": "#c8a2c8"}
FIXED_COLOUR = "#3060c0"
GRASP_CMAP = plt.get_cmap("tab10")


def read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray, list[str], dict[str, set[int]]]:
    """Nodes (N,3), tets (T,4) as 0-based rows, region name per tet, node sets by name (0-based)."""
    gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.open(str(path))
    tags, coords, _ = gmsh.model.mesh.getNodes()
    index = {int(t): i for i, t in enumerate(tags)}
    nodes = coords.reshape(-1, 3)
    tets: list[list[int]] = []
    regions: list[str] = []
    node_sets: dict[str, set[int]] = {}
    for dim, ptag in gmsh.model.getPhysicalGroups():
        name = gmsh.model.getPhysicalName(dim, ptag)
        for ent in gmsh.model.getEntitiesForPhysicalGroup(dim, ptag):
            types, _, conn = gmsh.model.mesh.getElements(dim, ent)
            for etype, c in zip(types, conn):
                if dim == 3 and etype == 4:
                    rows = c.reshape(-1, 4)
                    tets.extend([[index[int(v)] for v in r] for r in rows])
                    regions.extend([name] * len(rows))
                elif dim < 3:
                    node_sets.setdefault(name, set()).update(index[int(v)] for v in c)
    gmsh.finalize()
    return nodes, np.array(tets), regions, node_sets


def boundary(tets: np.ndarray, regions: list[str]) -> tuple[np.ndarray, list[str]]:
    """Faces used by exactly one tetrahedron, oriented outward, with the region of their tetrahedron."""
    local = [(1, 2, 3, 0), (0, 3, 2, 1), (0, 1, 3, 2), (0, 2, 1, 3)]
    count: Counter[tuple[int, ...]] = Counter()
    faces = []
    for t, tet in enumerate(tets):
        for a, b, c, _ in local:
            face = (tet[a], tet[b], tet[c])
            count[tuple(sorted(face))] += 1
            faces.append((face, t))
    tris, tri_regions = [], []
    for face, t in faces:
        if count[tuple(sorted(face))] == 1:
            tris.append(face)
            tri_regions.append(regions[t])
    return np.array(tris), tri_regions


def render(msh: Path, png: Path) -> None:
    nodes, tets, regions, node_sets = read_mesh(msh)
    tris, tri_regions = boundary(tets, regions)
    fixed = node_sets.get("fixed", set())
    grasps = sorted(k for k in node_sets if k.startswith("grasp_"))
    colours: list[str | tuple[float, float, float, float]] = []
    for tri, region in zip(tris, tri_regions):
        colour: str | tuple[float, float, float, float] = REGION_COLOURS.get(region, "#999999")
        if all(v in fixed for v in tri):
            colour = FIXED_COLOUR
        for i, g in enumerate(grasps):
            if all(v in node_sets[g] for v in tri):
                colour = GRASP_CMAP(i)
        colours.append(colour)

    mm = nodes * 1000.0
    views = [("anterior-inferior view", -25, 65), ("posterior-superior view", 35, -115), ("inferior view", -89, -90)]
    fig = plt.figure(figsize=(18, 6.5))
    for k, (title, elev, azim) in enumerate(views):
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        # Model y is superior: show it as the plot's vertical axis.
        verts = mm[tris][:, :, [0, 2, 1]]
        poly = Poly3DCollection(verts, facecolors=colours, edgecolors=(0, 0, 0, 0.12), linewidths=0.2)
        ax.add_collection3d(poly)
        lo, hi = mm.min(axis=0), mm.max(axis=0)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[2], hi[2])
        ax.set_zlim(lo[1], hi[1])
        ax.set_box_aspect((hi[0] - lo[0], hi[2] - lo[2], hi[1] - lo[1]))
        ax.view_init(elev=elev, azim=azim)
        ax.set_xlabel("x (mm, patient left)")
        ax.set_ylabel("z (mm, anterior)")
        ax.set_zlabel("y (mm, superior)")
        ax.set_title(title)
        if k == 0:
            for i, g in enumerate(grasps):
                centre = mm[sorted(node_sets[g])].mean(axis=0)
                ax.text(centre[0], centre[2] + 8, centre[1] - 6, g[-2:], color=GRASP_CMAP(i), fontsize=9)
    handles = [Rectangle((0, 0), 1, 1, color=c) for c in REGION_COLOURS.values()]
    labels = list(REGION_COLOURS)
    handles.append(Rectangle((0, 0), 1, 1, color=FIXED_COLOUR))
    labels.append("fixed")
    for i, g in enumerate(grasps):
        handles.append(Rectangle((0, 0), 1, 1, color=GRASP_CMAP(i)))
        labels.append(g)
    fig.legend(handles, labels, loc="lower center", ncol=8, frameon=False)
    fig.suptitle(f"{msh.name}: {len(nodes)} nodes, {len(tets)} tetrahedra, {len(tris)} surface triangles")
    fig.tight_layout(rect=(0, 0.06, 1, 0.95))
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("msh", type=Path)
    parser.add_argument("png", type=Path)
    args = parser.parse_args()
    render(args.msh, args.png)


if __name__ == "__main__":
    main()
