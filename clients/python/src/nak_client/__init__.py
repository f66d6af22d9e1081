"""Python client for nak, the real-time soft-tissue deformation server.

    from nak_client import Client, Grasp

    with Client("127.0.0.1:50051") as nak:
        mesh = nak.mesh()
        answer = nak.predict([Grasp(nodes=mesh.node_sets["grasp_04"][:10], displacement=(0, 0.02, 0))])
        answer.displacements  # numpy float32, (nodes, 3), metres

`AsyncClient` is the same over asyncio. Units are SI (metres, newtons).
"""

from ._aio import AsyncClient
from ._channel import Security
from ._sync import Client
from ._types import Grasp, Mesh, ModelInfo, Prediction, Selection, Status, StreamError, Timing

__all__ = [
    "AsyncClient",
    "Client",
    "Grasp",
    "Mesh",
    "ModelInfo",
    "Prediction",
    "Security",
    "Selection",
    "Status",
    "StreamError",
    "Timing",
]
