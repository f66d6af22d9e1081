"""A minimal nak client in Python (grpcio): fetch the mesh, lift grasp region 4 by 2 cm, read the field
and, from models that give them, the force each grasper exerts.

Start a server (cargo run --release -- serve), then: python examples/client.py [127.0.0.1:50051 [MODEL]]
MODEL defaults to the most accurate network shipped with the phantom; `kelvinlet` is the prior alone.
The stubs are generated from proto/ at start-up with grpcio-tools, so nothing generated is committed.
"""

from __future__ import annotations

import importlib
import sys
from dataclasses import dataclass
import tempfile
from pathlib import Path
from types import ModuleType
from typing import Any

import grpc
import numpy as np
from grpc_tools import protoc

PROTO_ROOT = Path(__file__).resolve().parent.parent / "proto"


def load_stubs() -> tuple[ModuleType, ModuleType]:
    """Compile nak/v1/deformation.proto into a temporary package and import it."""
    out = tempfile.mkdtemp(prefix="nak-stubs-")
    status = protoc.main(
        ["protoc", f"-I{PROTO_ROOT}", f"--python_out={out}", f"--grpc_python_out={out}", "nak/v1/deformation.proto"]
    )
    if status != 0:
        raise RuntimeError(f"protoc failed with status {status}")
    sys.path.insert(0, out)
    return importlib.import_module("nak.v1.deformation_pb2"), importlib.import_module("nak.v1.deformation_pb2_grpc")


BEST_MODEL = "pod-res-big"


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
    pb, rpc = load_stubs()
    with grpc.insecure_channel(target) as channel:
        stub = rpc.DeformationStub(channel)
        mesh = stub.GetMesh(pb.GetMeshRequest())
        positions = np.frombuffer(mesh.positions, dtype="<f4").reshape(-1, 3)
        grasp_04 = next(s for s in mesh.node_sets if s.name == "grasp_04")
        request = pb.PredictRequest(
            model=model,
            grasps=[pb.Grasp(nodes=list(grasp_04.nodes)[:10], displacement=pb.Vec3(x=0.0, y=0.02, z=0.0))],
        )
        response = stub.Predict(request)
        u = np.frombuffer(response.displacements, dtype="<f4").reshape(-1, 3)
        forces = np.array([[f.x, f.y, f.z] for f in response.grasp_forces]) if response.grasp_forces else None
        print(
            f"{model}: {len(positions)} nodes; {response.interaction_points} interaction points; "
            f"largest displacement {1e3 * np.linalg.norm(u, axis=1).max():.1f} mm; "
            f"server {response.timing.total_us:.0f} µs"
        )
        if forces is not None:
            print(f"grasper force {forces[0].round(4)} N")
        return Answer(u, forces)


if __name__ == "__main__":
    main(*sys.argv[1:3])
