"""Writing the mesh as MSH 4.1 with gmsh: one volume physical group and a physical group per node set.

The tetrahedra go on one discrete volume in the physical group `organ` (tag 1, the region's `label` in
model.toml). Each node set (`fixed`, the grasp regions) is a point physical group: a discrete point
entity holding one point element per node, which nak reads as the set's nodes (docs/meshes.md: "surface
(or point) physical groups"). Point groups rather than surface groups (the phantom's, made of boundary
triangles) because a selection is a set of nodes: neighbouring grasp regions that share no node, or a
`vertices:` selection of single nodes, cannot be written as groups of triangles. Nodes are written in
the order given, so node i here is node i in nak.
"""

from __future__ import annotations

from pathlib import Path

import gmsh

from .meshing import VolumeMesh
from .selections import NodeSet

REGION = "organ"
REGION_TAG = 1


def write_msh(path: Path, mesh: VolumeMesh, node_sets: list[NodeSet], binary: bool) -> None:
    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add(REGION)
        volume = gmsh.model.addDiscreteEntity(3)
        gmsh.model.mesh.addNodes(3, volume, range(1, len(mesh.nodes) + 1), mesh.nodes.ravel().tolist())
        gmsh.model.mesh.addElementsByType(volume, 4, [], (mesh.tets + 1).ravel().tolist())
        gmsh.model.addPhysicalGroup(3, [volume], REGION_TAG, name=REGION)
        for node_set in node_sets:
            point = gmsh.model.addDiscreteEntity(0)
            gmsh.model.mesh.addElementsByType(point, 15, [], (node_set.nodes + 1).tolist())
            gmsh.model.addPhysicalGroup(0, [point], name=node_set.name)
        gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
        gmsh.option.setNumber("Mesh.Binary", 1 if binary else 0)
        gmsh.option.setNumber("Mesh.SaveAll", 0)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
