"""The Kelvinlet-regularization distribution q (docs/design.md §5), as in the paper's public training code.

A surface node drawn uniformly plus its 3–7 nearest surface neighbours (the mesh's grasp neighbour
range), all moved by one displacement: direction uniform in a cone of half-angle 30° around their mean
outward normal, signed magnitude uniform in (−10, 20) mm (push in up to 1 cm, pull out up to 2 cm).
"""

from __future__ import annotations

import math

import torch

from .dataset import Mesh

CONE_HALF_ANGLE = math.radians(30.0)
MAGNITUDE_M = (-0.010, 0.020)


class QSampler:
    def __init__(self, mesh: Mesh, generator: torch.Generator) -> None:
        self.mesh = mesh
        self.generator = generator
        surface = mesh.positions[mesh.surface_nodes]
        most = mesh.neighbours[1] + 1
        # Nearest surface nodes of every surface node (itself first), by index into surface_nodes.
        self.nearest = torch.cdist(surface, surface).topk(most, largest=False).indices

    def draw(self, count: int) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Node ids [K] and per-node displacements [K, 3] (metres) of `count` samples."""
        g = self.generator
        low, high = self.mesh.neighbours
        nodes, displacements = [], []
        for _ in range(count):
            centre = int(torch.randint(len(self.mesh.surface_nodes), (1,), generator=g))
            extra = int(torch.randint(low, high + 1, (1,), generator=g))
            ids = self.mesh.surface_nodes[self.nearest[centre, : extra + 1]]
            normal = self.mesh.normals[ids].sum(0)
            normal = normal / normal.norm().clamp_min(1e-12)
            direction = _in_cone(normal, CONE_HALF_ANGLE, g)
            magnitude = MAGNITUDE_M[0] + (MAGNITUDE_M[1] - MAGNITUDE_M[0]) * float(torch.rand((), generator=g))
            nodes.append(ids)
            displacements.append((magnitude * direction).expand(len(ids), 3).clone())
        return nodes, displacements


def _in_cone(axis: torch.Tensor, half_angle: float, g: torch.Generator) -> torch.Tensor:
    """A direction uniform (by solid angle) within `half_angle` of the unit vector `axis`."""
    cos_theta = 1.0 - float(torch.rand((), generator=g)) * (1.0 - math.cos(half_angle))
    sin_theta = math.sqrt(max(0.0, 1.0 - cos_theta * cos_theta))
    phi = 2.0 * math.pi * float(torch.rand((), generator=g))
    helper = torch.tensor([1.0, 0.0, 0.0], dtype=axis.dtype)
    if abs(float(axis[0])) > 0.9:
        helper = torch.tensor([0.0, 1.0, 0.0], dtype=axis.dtype)
    e1 = torch.linalg.cross(axis, helper)
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(axis, e1)
    return cos_theta * axis + sin_theta * (math.cos(phi) * e1 + math.sin(phi) * e2)
