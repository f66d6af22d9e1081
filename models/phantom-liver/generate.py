"""Generate the nak phantom liver: a labelled, conforming tetrahedral mesh built with gmsh (OpenCASCADE).

The paper's patient mesh is not public, so nak ships this phantom. Geometry (metres; x to the patient's
left, y superior (gravity along -y), z anterior):

* liver: a thick right lobe and a thin left lobe (two ellipsoids, fused), cut by a tilted plane whose
  intersection with the anterior surface is the sharp anterior-inferior ridge that graspers lift;
* gallbladder: a pear (fundus sphere + tapered body) seated in a fossa on the inferior surface;
* ducts: the cystic duct leaving the gallbladder neck and joining the common bile duct, which runs from the
  hilum down and out of the liver; its distal end and the hepatic end are fixed.

Boundary-condition patches are imprinted on the surface by fragmenting with small spheres, so that each one
is its own geometric surface and can carry a physical group: ``fixed`` (bare area + distal duct end) and
``grasp_01`` ... ``grasp_10`` (clusters along the ridge).

Run ``python models/phantom-liver/generate.py`` (see docs/meshes.md) to rewrite liver.msh, liver-coarse.msh and
phantom-liver.png. Meshing is single-threaded with a fixed seed, so the output is deterministic.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

import gmsh
import numpy as np

HERE = Path(__file__).resolve().parent

# Surface points of the ridge where grasp patches are centred: found by ray casting (see ridge_points).
GRASP_COUNT = 10
GRASP_PATCH_RADIUS = 0.0075
BARE_AREA_RADIUS = 0.030


@dataclass(frozen=True)
class Resolution:
    """Target element sizes (metres) for one output mesh."""

    name: str
    liver: float
    gallbladder: float
    ducts: float


PAPER_SCALE = Resolution("liver", liver=0.0056, gallbladder=0.0045, ducts=0.0027)
COARSE = Resolution("liver-coarse", liver=0.0135, gallbladder=0.0095, ducts=0.0040)


# Lobes as ellipsoids: (centre, semi-axes). The right lobe is thick, the left lobe thin and flat.
LOBES = (
    ((-0.040, 0.000, 0.000), (0.075, 0.078, 0.060)),
    ((0.050, 0.004, 0.004), (0.066, 0.034, 0.046)),
)
# The visceral (inferior) face is the plane y = Y0 + TILT x - SLOPE z: it faces down and back, rises
# towards the posterior and to the left, and meets the anterior surface in the acute anterior-inferior
# ridge that runs from low on the right lobe to the tip of the left lobe.
VISCERAL_Y0 = -0.025
VISCERAL_TILT = 0.30
VISCERAL_SLOPE = 0.60


def visceral_y(x: float, z: float) -> float:
    return VISCERAL_Y0 + VISCERAL_TILT * x - VISCERAL_SLOPE * z


def liver_body(occ: type[gmsh.model.occ]) -> int:
    """Right lobe + left lobe, fused, with everything below the visceral plane cut away."""
    lobes = []
    for (cx, cy, cz), (a, b, c) in LOBES:
        tag = occ.addSphere(cx, cy, cz, 1.0)
        occ.dilate([(3, tag)], cx, cy, cz, a, b, c)
        lobes.append((3, tag))
    fused, _ = occ.fuse(lobes[:1], lobes[1:])
    cutter = occ.addBox(-0.3, -0.6, -0.3, 0.6, 0.6, 0.6)
    # Shear the half-space y < 0 onto the visceral plane.
    shear = [1.0, 0.0, 0.0, 0.0, VISCERAL_TILT, 1.0, -VISCERAL_SLOPE, VISCERAL_Y0, 0.0, 0.0, 1.0, 0.0]
    occ.affineTransform([(3, cutter)], shear)
    body, _ = occ.cut(fused, [(3, cutter)])
    return int(body[0][1])


GALLBLADDER_NECK = (-0.030, visceral_y(-0.030, -0.040) - 0.006, -0.040)


def gallbladder_body(occ: type[gmsh.model.occ]) -> int:
    """A pear about 8 cm long lying along the visceral face, a third of it sunk into its fossa."""
    fundus = np.array([-0.040, visceral_y(-0.040, 0.018) - 0.006, 0.018])
    neck = np.array(GALLBLADDER_NECK)
    f = occ.addSphere(*fundus, 0.0165)
    body = occ.addCone(*fundus, *(neck - fundus), 0.0165, 0.0058)
    n = occ.addSphere(*neck, 0.0062)
    pear, _ = occ.fuse([(3, f)], [(3, body), (3, n)])
    return int(pear[0][1])


def duct_bodies(occ: type[gmsh.model.occ]) -> tuple[int, tuple[float, float, float]]:
    """Cystic duct from the neck to the common bile duct; the common duct runs down from the hilum.

    Returns the fused duct volume and the centre of the common duct's distal (fixed) end.
    """
    neck = np.array(GALLBLADDER_NECK)
    hilum = np.array([-0.005, visceral_y(-0.005, -0.035) + 0.004, -0.035])
    distal = np.array([-0.015, -0.105, -0.030])
    junction = hilum + 0.55 * (distal - hilum)
    common = occ.addCylinder(*hilum, *(distal - hilum), 0.0036)
    cystic = occ.addCylinder(*neck, *(junction - neck), 0.0028)
    joint = occ.addSphere(*junction, 0.0036)
    ducts, _ = occ.fuse([(3, common)], [(3, cystic), (3, joint)])
    if len(ducts) != 1:
        raise RuntimeError(f"cystic and common ducts do not join: {ducts}")
    return ducts[0][1], (float(distal[0]), float(distal[1]), float(distal[2]))


def ridge_points() -> list[np.ndarray]:
    """Centres of the grasp patches: the front-most points where the visceral plane meets a lobe."""
    points = []
    for x in np.linspace(-0.080, 0.095, GRASP_COUNT):
        best = None
        for (cx, cy, cz), (a, b, c) in LOBES:
            # Substitute y = (Y0 + TILT x) - s z into the ellipsoid equation: A z^2 + B z + C = 0.
            s, dy0 = VISCERAL_SLOPE, VISCERAL_Y0 + VISCERAL_TILT * x - cy
            qa = s * s / (b * b) + 1.0 / (c * c)
            qb = -2.0 * s * dy0 / (b * b) - 2.0 * cz / (c * c)
            qc = ((x - cx) / a) ** 2 + (dy0 / b) ** 2 + (cz / c) ** 2 - 1.0
            disc = qb * qb - 4.0 * qa * qc
            if disc < 0.0:
                continue
            z = (-qb + math.sqrt(disc)) / (2.0 * qa)
            if best is None or z > best[2]:
                best = np.array([x, visceral_y(x, z), z])
        if best is None:
            raise RuntimeError(f"no ridge at x = {x}")
        points.append(best)
    return points


def bare_area_centre() -> np.ndarray:
    """Posterior-superior surface of the right lobe, where the liver lies against diaphragm and cava."""
    (cx, cy, cz), axes = LOBES[0]
    d = np.array([0.15, 0.55, -0.82])
    t = 1.0 / math.sqrt(sum((di / ai) ** 2 for di, ai in zip(d, axes)))
    return np.array([cx, cy, cz]) + t * d


def centred_box(occ: type[gmsh.model.occ], centre: np.ndarray, half: float) -> int:
    return int(occ.addBox(*(centre - half), 2 * half, 2 * half, 2 * half))


def boundary_surfaces() -> list[int]:
    """Surfaces that bound exactly one volume: the outer skin of the organ."""
    skin = []
    for _, tag in gmsh.model.getEntities(2):
        up, _ = gmsh.model.getAdjacencies(2, tag)
        if len(up) == 1:
            skin.append(tag)
    return skin


def build(res: Resolution, out_dir: Path) -> Path:
    gmsh.initialize(interruptible=False)
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.option.setNumber("General.NumThreads", 1)
    gmsh.option.setNumber("Mesh.RandomSeed", 1)
    gmsh.model.add(res.name)
    occ = gmsh.model.occ

    liver = liver_body(occ)
    gall = gallbladder_body(occ)
    ducts, distal = duct_bodies(occ)
    # Give each point of space to one organ: the gallbladder owns its fossa, the liver owns the hilar
    # part of the duct, and the ducts keep what lies outside both.
    ducts_out, _ = occ.cut([(3, ducts)], [(3, liver), (3, gall)], removeObject=True, removeTool=False)
    liver_out, _ = occ.cut([(3, liver)], [(3, gall)], removeObject=True, removeTool=False)
    occ.synchronize()
    liver_vols = [t for _, t in liver_out]
    duct_vols = [t for _, t in ducts_out]

    grasp_centres = ridge_points()
    bare_centre = bare_area_centre()
    # Boxes rather than spheres: their faces are not periodic, which keeps the surface mesher robust.
    markers = [centred_box(occ, c, GRASP_PATCH_RADIUS) for c in grasp_centres]
    bare = centred_box(occ, bare_centre, BARE_AREA_RADIUS)

    organs = [(3, t) for t in liver_vols] + [(3, gall)] + [(3, t) for t in duct_vols]
    tools = [(3, m) for m in markers] + [(3, bare)]
    _, parent_map = occ.fragment(organs, tools)
    occ.synchronize()

    def pieces(index: int) -> list[int]:
        return [t for d, t in parent_map[index] if d == 3]

    n_liver, n_gall = len(liver_vols), 1
    liver_pieces = {t for i in range(n_liver) for t in pieces(i)}
    gall_pieces = set(pieces(n_liver))
    duct_pieces = {t for i in range(n_liver + n_gall, len(organs)) for t in pieces(i)}
    # Marker spheres outside the organs are not tissue: remove them with their boundaries.
    organ_pieces = liver_pieces | gall_pieces | duct_pieces
    stray = [(3, t) for _, t in gmsh.model.getEntities(3) if t not in organ_pieces]
    occ.remove(stray, recursive=True)
    occ.synchronize()
    # Marker pieces inside the gallbladder or ducts stay with their organ (fragment keeps parentage).
    liver_pieces -= gall_pieces | duct_pieces

    gmsh.model.addPhysicalGroup(3, sorted(liver_pieces), name="liver")
    gmsh.model.addPhysicalGroup(3, sorted(gall_pieces), name="gallbladder")
    gmsh.model.addPhysicalGroup(3, sorted(duct_pieces), name="ducts")

    skin = boundary_surfaces()

    def skin_within(centre: np.ndarray, radius: float, owners: set[int]) -> list[int]:
        found = []
        for tag in skin:
            up, _ = gmsh.model.getAdjacencies(2, tag)
            if up[0] not in owners:
                continue
            com = np.array(occ.getCenterOfMass(2, tag))
            if np.max(np.abs(com - centre)) < radius:
                found.append(tag)
        return found

    distal_cap = skin_within(np.array(distal), 0.004, duct_pieces)
    fixed = skin_within(bare_centre, BARE_AREA_RADIUS, liver_pieces) + distal_cap
    if not distal_cap:
        raise RuntimeError("distal duct end not found on the surface")
    gmsh.model.addPhysicalGroup(2, sorted(fixed), name="fixed")
    for i, centre in enumerate(grasp_centres, start=1):
        patch = skin_within(centre, GRASP_PATCH_RADIUS, liver_pieces)
        if not patch:
            raise RuntimeError(f"grasp patch {i} at {centre} has no surface")
        gmsh.model.addPhysicalGroup(2, sorted(patch), name=f"grasp_{i:02d}")

    size_by_volume = {}
    for t in liver_pieces:
        size_by_volume[t] = res.liver
    for t in gall_pieces:
        size_by_volume[t] = res.gallbladder
    for t in duct_pieces:
        size_by_volume[t] = res.ducts
    # Each node takes the size of the finest volume it touches, so the ducts refine their surroundings.
    for vol, size in sorted(size_by_volume.items(), key=lambda kv: -kv[1]):
        points = gmsh.model.getBoundary([(3, vol)], combined=False, recursive=True)
        gmsh.model.mesh.setSize(points, size)
    fields = []
    for vol, size in size_by_volume.items():
        f = gmsh.model.mesh.field.add("Constant")
        gmsh.model.mesh.field.setNumbers(f, "VolumesList", [vol])
        gmsh.model.mesh.field.setNumber(f, "VIn", size)
        gmsh.model.mesh.field.setNumber(f, "VOut", 1.0)
        fields.append(f)
    duct_surfaces = [
        t for _, t in gmsh.model.getBoundary([(3, v) for v in duct_pieces], combined=False, oriented=False)
    ]
    dist = gmsh.model.mesh.field.add("Distance")
    gmsh.model.mesh.field.setNumbers(dist, "SurfacesList", duct_surfaces)
    grade = gmsh.model.mesh.field.add("Threshold")
    gmsh.model.mesh.field.setNumber(grade, "InField", dist)
    gmsh.model.mesh.field.setNumber(grade, "SizeMin", res.ducts)
    gmsh.model.mesh.field.setNumber(grade, "SizeMax", res.liver)
    gmsh.model.mesh.field.setNumber(grade, "DistMin", 0.002)
    gmsh.model.mesh.field.setNumber(grade, "DistMax", 0.03)
    fields.append(grade)
    smallest = gmsh.model.mesh.field.add("Min")
    gmsh.model.mesh.field.setNumbers(smallest, "FieldsList", fields)
    gmsh.model.mesh.field.setAsBackgroundMesh(smallest)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.Algorithm3D", 1)
    gmsh.option.setNumber("Mesh.Optimize", 1)
    gmsh.option.setNumber("Mesh.OptimizeNetgen", 1)
    gmsh.model.mesh.generate(3)

    gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
    gmsh.option.setNumber("Mesh.Binary", 0)
    gmsh.option.setNumber("Mesh.SaveAll", 0)
    path = out_dir / f"{res.name}.msh"
    gmsh.write(str(path))
    node_tags, _, _ = gmsh.model.mesh.getNodes()
    tets, _ = gmsh.model.mesh.getElementsByType(4)
    print(f"{path.name}: {len(node_tags)} nodes, {len(tets)} tetrahedra")
    gmsh.finalize()
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=HERE, help="output directory")
    parser.add_argument("--only", choices=["liver", "liver-coarse"], help="build one mesh")
    args = parser.parse_args()
    for res in (PAPER_SCALE, COARSE):
        if args.only in (None, res.name):
            build(res, args.out)


if __name__ == "__main__":
    main()
