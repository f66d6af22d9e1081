"""What the client hands out and takes in: plain dataclasses with numpy arrays, converted to and from
nak's protobuf messages here and nowhere else."""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from ._generated import deformation_pb2 as pb

Vector = Sequence[float] | npt.NDArray[np.floating[Any]]


class Selection(enum.IntEnum):
    """Which nodes an answer holds."""

    ALL = pb.NODE_SELECTION_ALL
    SURFACE = pb.NODE_SELECTION_SURFACE
    LIST = pb.NODE_SELECTION_LIST


@dataclass(frozen=True)
class Grasp:
    """One grasper: the surface nodes it holds (or those within `radius` of `point`; the nearest one
    when `radius` is 0), moved by `displacement` (metres)."""

    displacement: Vector
    nodes: Sequence[int] | npt.NDArray[np.integer[Any]] = ()
    point: Vector | None = None
    radius: float = 0.0

    def message(self) -> pb.Grasp:
        grasp = pb.Grasp(nodes=[int(n) for n in self.nodes], radius=self.radius, displacement=_vec3(self.displacement))
        if self.point is not None:
            grasp.point.CopyFrom(_vec3(self.point))
        return grasp


def _vec3(v: Vector) -> pb.Vec3:
    x, y, z = (float(c) for c in v)
    return pb.Vec3(x=x, y=y, z=z)


@dataclass(frozen=True)
class Mesh:
    """The served mesh: positions (N, 3) float32 metres, outward surface triangles (T, 3), node sets."""

    name: str
    content_hash: str
    positions: npt.NDArray[np.float32]
    surface_triangles: npt.NDArray[np.uint32]
    surface_nodes: npt.NDArray[np.uint32]
    node_sets: dict[str, npt.NDArray[np.uint32]]
    regions: dict[str, float]
    """Region name → volume (m³)."""

    @staticmethod
    def from_message(m: pb.Mesh) -> Mesh:
        return Mesh(
            name=m.name,
            content_hash=m.content_hash,
            positions=np.frombuffer(m.positions, dtype="<f4").reshape(-1, 3),
            surface_triangles=np.frombuffer(m.surface_triangles, dtype="<u4").reshape(-1, 3),
            surface_nodes=np.array(m.surface_nodes, dtype=np.uint32),
            node_sets={s.name: np.array(s.nodes, dtype=np.uint32) for s in m.node_sets},
            regions={r.name: r.volume_m3 for r in m.regions},
        )


@dataclass(frozen=True)
class ModelInfo:
    name: str
    kind: str
    """prior, exact or neural."""
    regime: str
    forces: str
    """exact, estimate or unavailable."""
    metadata: dict[str, str]

    @staticmethod
    def from_message(m: pb.ModelInfo) -> ModelInfo:
        return ModelInfo(
            name=m.name,
            kind=pb.ModelKind.Name(m.kind).removeprefix("MODEL_KIND_").lower(),
            regime=m.regime,
            forces=pb.Forces.Name(m.forces).removeprefix("FORCES_").lower(),
            metadata=dict(m.metadata),
        )


@dataclass(frozen=True)
class Timing:
    """The server's own time per stage, microseconds."""

    resolve_us: float
    queue_us: float
    prior_us: float
    network_us: float
    total_us: float


@dataclass(frozen=True)
class Prediction:
    """An answer: displacements (n, 3) float32 metres, the node of each row (every node, in order, when
    the selection was ALL), each grasper's force (g, 3) newtons (empty when the model gives none)."""

    model: str
    sequence: int
    displacements: npt.NDArray[np.float32]
    node_ids: npt.NDArray[np.uint32] | None
    forces: npt.NDArray[np.float32]
    interaction_points: int
    timing: Timing

    @staticmethod
    def from_message(m: pb.PredictResponse) -> Prediction:
        t = m.timing
        return Prediction(
            model=m.model,
            sequence=m.sequence,
            displacements=np.frombuffer(m.displacements, dtype="<f4").reshape(-1, 3),
            node_ids=np.array(m.node_ids, dtype=np.uint32) if m.node_ids else None,
            forces=np.array([[f.x, f.y, f.z] for f in m.grasp_forces], dtype=np.float32).reshape(-1, 3),
            interaction_points=m.interaction_points,
            timing=Timing(t.resolve_us, t.queue_us, t.prior_us, t.network_us, t.total_us),
        )


@dataclass(frozen=True)
class Status:
    version: str
    uptime_ms: int
    admission: dict[str, int] = field(default_factory=dict)
    recorder: dict[str, int | str | bool] = field(default_factory=dict)
    refused_models: dict[str, str] = field(default_factory=dict)

    @staticmethod
    def from_message(m: pb.ServerStatus) -> Status:
        a, r = m.admission, m.recorder
        return Status(
            version=m.version,
            uptime_ms=m.uptime_ms,
            admission={
                "max_in_flight": a.max_in_flight,
                "in_flight": a.in_flight,
                "refused": a.refused,
                "expired": a.expired,
                "abandoned": a.abandoned,
            },
            recorder={"enabled": r.enabled, "recorded": r.recorded, "dropped": r.dropped, "error": r.error},
            refused_models={x.origin: x.reason for x in m.refused_models},
        )


class StreamError(RuntimeError):
    """A message of a stream that the server refused (the stream goes on)."""

    def __init__(self, sequence: int, code: int, message: str) -> None:
        super().__init__(f"message {sequence} refused ({code}): {message}")
        self.sequence, self.code, self.message = sequence, code, message


NodeChoice = Selection | Sequence[int] | npt.NDArray[np.integer[Any]]
"""Which nodes to answer for: every node, the surface, or these node ids."""


def request(grasps: Sequence[Grasp], model: str, select: NodeChoice, sequence: int) -> pb.PredictRequest:
    message = pb.PredictRequest(model=model, grasps=[g.message() for g in grasps], sequence=sequence)
    if isinstance(select, Selection):
        message.selection = int(select)  # type: ignore[assignment]
    else:
        message.selection = pb.NODE_SELECTION_LIST
        message.nodes.extend(int(n) for n in select)
    return message


def answer(m: pb.PredictResponse) -> Prediction:
    """A stream message's answer, or its refusal raised."""
    if m.HasField("error"):
        raise StreamError(m.sequence, m.error.code, m.error.message)
    return Prediction.from_message(m)
