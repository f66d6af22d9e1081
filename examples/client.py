"""A minimal nak client in Python (the nak-client package, clients/python): fetch the mesh, lift grasp
region 4 by 2 cm, read the field and, from models that give them, the force each grasper exerts.

Start a server (cargo run --release -- serve), then: python examples/client.py [127.0.0.1:50051 [MODEL]]
MODEL defaults to the most accurate network shipped with the phantom; `kelvinlet` is the prior alone.
scripts/setup-python installs the package (`pip install ./clients/python`), compiling its stubs from proto/.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np
from nak_client import Client, Grasp

BEST_MODEL = "pod-res-big"


def load_stubs() -> tuple[ModuleType, ModuleType]:
    """The raw protobuf messages and gRPC stub, for scripts that build requests themselves."""
    from nak_client._generated import deformation_pb2, deformation_pb2_grpc

    return deformation_pb2, deformation_pb2_grpc


def two_graspers(pb: ModuleType, mesh: Any) -> list[Any]:
    """Two graspers of ten nodes each (grasp regions 3 and 8) moved apart: K = 20, the size of the
    paper's two-grasper requests on average; the scripts that time the prior all send these."""
    sets = {s.name: list(s.nodes) for s in mesh.node_sets}
    return [
        pb.Grasp(nodes=sets["grasp_03"][:10], displacement=pb.Vec3(x=0.01, y=0.03, z=-0.01)),
        pb.Grasp(nodes=sets["grasp_08"][:10], displacement=pb.Vec3(x=-0.02, y=0.02, z=0.015)),
    ]


@dataclass
class Answer:
    """Displacements (n, 3) in metres, and per grasp the force (N) it exerts on the tissue, or None when
    the model gives no forces (ModelInfo.forces)."""

    displacements: np.ndarray
    grasp_forces: np.ndarray | None


def main(target: str = "127.0.0.1:50051", model: str = BEST_MODEL) -> Answer:
    with Client(target) as nak:
        mesh = nak.mesh()
        lift = Grasp(nodes=mesh.node_sets["grasp_04"][:10], displacement=(0.0, 0.02, 0.0))
        answer = nak.predict([lift], model=model)
    u = answer.displacements
    print(
        f"{model}: {len(mesh.positions)} nodes; {answer.interaction_points} interaction points; "
        f"largest displacement {1e3 * np.linalg.norm(u, axis=1).max():.1f} mm; "
        f"server {answer.timing.total_us:.0f} µs"
    )
    forces = answer.forces if len(answer.forces) else None
    if forces is not None:
        print(f"grasper force {forces[0].round(4)} N")
    return Answer(u, forces)


if __name__ == "__main__":
    main(*sys.argv[1:3])
