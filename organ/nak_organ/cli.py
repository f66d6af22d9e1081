"""`python -m nak_organ mesh SURFACE --units mm --out DIR --fixed SPEC [--grasp NAME=SPEC]…`

Reads a closed triangle surface, refuses it with one line per problem when it cannot enclose an organ,
tetrahedralizes it with gmsh to about --target-nodes nodes, selects the node sets, writes organ.msh and
model.toml, and places them in DIR once `nak mesh info` accepts them (placing.py); `nak serve --mesh DIR`
then takes DIR. docs/your-own-organ.md describes the options; exit status 2 means the input was refused.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np

from .boundary import Boundary, match_boundary
from .checks import bounding_diagonal, check_surface
from .errors import OrganInputError
from .geometry import enclosed_volume
from .meshing import VolumeMesh, tetrahedralize
from .model_toml import model_toml
from .msh import write_msh
from .placing import MSH_NAME, default_nak, place, staging_folder
from .quality import radius_ratios, tet_volumes
from .reading import METRES_PER_UNIT, read_surface
from .regions import split_free_surface
from .selections import NodeSet, check_selections, node_sets, parse_fixed, parse_grasp


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m nak_organ", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    mesh = commands.add_parser("mesh", help="a labelled tetrahedral mesh and model.toml from a closed surface")
    mesh.add_argument("surface", type=Path, help="closed triangle surface: .stl (ASCII or binary), .obj, .ply")
    mesh.add_argument("--units", required=True, choices=list(METRES_PER_UNIT), help="units of the file's coordinates")
    mesh.add_argument("--out", type=Path, required=True, help="directory for organ.msh and model.toml")
    mesh.add_argument(
        "--fixed",
        action="append",
        default=[],
        metavar="SPEC",
        help="nodes held in place (repeatable, their union): sphere:x,y,z,r | box:x0,y0,z0,x1,y1,z1 | "
        "vertices:i,j,… | group:NAME, in the surface's units",
    )
    mesh.add_argument("--grasp", action="append", default=[], metavar="NAME=SPEC", help="a grasp region (repeatable)")
    mesh.add_argument(
        "--grasp-regions",
        type=int,
        metavar="N",
        help="without --grasp: split the free surface into N regions of similar area (default 10)",
    )
    mesh.add_argument("--target-nodes", type=int, default=10_000, help="about this many nodes (default 10000)")
    mesh.add_argument("--name", help="the mesh's name in model.toml (default: the surface's file name stem)")
    mesh.add_argument(
        "--feature-angle",
        type=float,
        default=40.0,
        metavar="DEG",
        help="faces meeting at more than this angle keep their edge sharp (default 40; 180 keeps none)",
    )
    mesh.add_argument("--binary", action="store_true", help="write binary MSH (default ASCII)")
    mesh.add_argument(
        "--nak",
        type=Path,
        default=default_nak(),
        help="the nak binary whose `nak mesh info` checks the files before they are placed in --out "
        "(default: $NAK_BIN, else the repository's target/release/nak; without one they are placed unchecked)",
    )
    mesh.add_argument(
        "--displacement-min-mm",
        metavar="X,Y,Z",
        help="sampling cuboid's low corner, mm (write --displacement-min-mm=-90,-90,-60)",
    )
    mesh.add_argument("--displacement-max-mm", metavar="X,Y,Z", help="sampling cuboid's high corner (mm)")
    args = parser.parse_args(argv)
    try:
        run_mesh(args)
    except OrganInputError as e:
        for problem in e.problems:
            print(f"error: {problem}", file=sys.stderr)
        return 2
    return 0


def run_mesh(args: argparse.Namespace) -> None:
    displacement = _displacement_option(args.displacement_min_mm, args.displacement_max_mm)
    if args.grasp and args.grasp_regions is not None:
        raise OrganInputError(
            ["--grasp-regions splits the free surface when no --grasp is given: give one or the other"]
        )
    regions = 10 if args.grasp_regions is None else args.grasp_regions
    if regions < 1 or args.target_nodes < 100:
        raise OrganInputError(["--grasp-regions must be at least 1 and --target-nodes at least 100"])
    if args.out.exists() and not args.out.is_dir():
        # Before meshing, which may take a while; other reasons not to write there surface when it is made.
        raise OrganInputError([f"--out {args.out}: cannot write there: it is a file, not a directory"])
    fixed = [parse_fixed(s) for s in args.fixed]
    grasps = [parse_grasp(s) for s in args.grasp]
    surface = read_surface(args.surface, args.units)
    check_surface(surface)
    check_selections(fixed, grasps, surface)

    mesh = tetrahedralize(surface, args.target_nodes, args.feature_angle)
    boundary = match_boundary(mesh, surface)
    fixed_set, grasp_sets = node_sets(fixed, grasps, boundary, surface)
    if not grasp_sets:
        grasp_sets = split_free_surface(boundary, fixed_set, regions)

    text = model_toml(
        name=args.name or args.surface.stem,
        source=args.surface,
        msh_name=MSH_NAME,
        diagonal_m=bounding_diagonal(mesh.nodes),
        grasp_regions=[g.name for g in grasp_sets],
        displacement_mm=displacement,
    )
    staging = staging_folder(args.out)
    try:
        write_msh(staging / MSH_NAME, mesh, [fixed_set, *grasp_sets], args.binary)
        (staging / "model.toml").write_text(text)
        checked = place(staging, args.out, args.nak)
    finally:
        # Left behind only when writing failed: placed and refused files have moved out of it.
        shutil.rmtree(staging, ignore_errors=True)
    volume = abs(enclosed_volume(surface.vertices, surface.faces))
    print(summary(args.out, mesh, boundary, volume, fixed_set, grasp_sets, checked))


def _displacement_option(low: str | None, high: str | None) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
    if low is None and high is None:
        return None
    problem = OrganInputError(
        ["--displacement-min-mm and --displacement-max-mm go together, each x,y,z in mm, min below max"]
    )
    if low is None or high is None:
        raise problem
    try:
        lo, hi = tuple(float(v) for v in low.split(",")), tuple(float(v) for v in high.split(","))
    except ValueError:
        raise problem from None
    if len(lo) != 3 or len(hi) != 3 or not all(a < b for a, b in zip(lo, hi)):
        raise problem
    return lo, hi


def summary(
    out: Path,
    mesh: VolumeMesh,
    boundary: Boundary,
    input_volume: float,
    fixed: NodeSet,
    grasps: list[NodeSet],
    checked: str,
) -> str:
    """What was written, for the terminal."""
    quality = radius_ratios(mesh.nodes, mesh.tets)
    tries = ", ".join(f"{n} at {h * 1000:.2f} mm" for h, n in mesh.tries)
    lines = [
        f"wrote       {out / MSH_NAME} and {out / 'model.toml'}",
        f"nodes       {len(mesh.nodes)} ({len(boundary.nodes)} on the surface; tries: {tries})",
        f"tetrahedra  {len(mesh.tets)}",
        f"volume      {tet_volumes(mesh.nodes, mesh.tets).sum() * 1e6:.1f} mL (the input surface encloses "
        f"{input_volume * 1e6:.1f} mL)",
        f"quality     radius ratio 3r/R min {quality.min():.3f}, median {np.median(quality):.3f} (1 = regular)",
        f"deviation   surface nodes from the input surface: max {boundary.node_deviation * 1000:.3f} mm; "
        f"input vertices from the mesh surface: max {boundary.input_deviation * 1000:.3f} mm",
        f"checked     {checked}",
        "node sets",
    ]
    for node_set in [fixed, *grasps]:
        covered = boundary.areas[np.searchsorted(boundary.nodes, node_set.nodes)].sum()
        lines.append(f"  {node_set.name:<12} {len(node_set.nodes):>6} nodes  {covered * 1e4:8.2f} cm²")
    return "\n".join(lines)
