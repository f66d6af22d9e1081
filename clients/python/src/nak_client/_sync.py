"""The blocking client."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from types import TracebackType

import grpc

from ._channel import Security, Session
from ._generated import deformation_pb2 as pb
from ._generated import deformation_pb2_grpc as rpc
from ._types import Grasp, Mesh, ModelInfo, NodeChoice, Prediction, Selection, Status, StreamError, answer, request


class Client(Session):
    """A connection to one nak server (`target` is host:port). Use as a context manager, or `close()`."""

    def __init__(self, target: str = "127.0.0.1:50051", security: Security | None = None) -> None:
        super().__init__(security)
        security, options = self.security, self.security.options()
        if security.uses_tls():
            self._channel = grpc.secure_channel(target, security.credentials(), options)
        else:
            self._channel = grpc.insecure_channel(target, options)
        self._stub = rpc.DeformationStub(self._channel)  # type: ignore[no-untyped-call]

    def mesh(self, name: str = "") -> Mesh:
        return Mesh.from_message(self._stub.GetMesh(pb.GetMeshRequest(mesh=name), metadata=self._metadata))

    def models(self) -> list[ModelInfo]:
        reply = self._stub.ListModels(pb.ListModelsRequest(), metadata=self._metadata)
        return [ModelInfo.from_message(m) for m in reply.models]

    def status(self) -> Status:
        return Status.from_message(self._stub.GetStatus(pb.GetStatusRequest(), metadata=self._metadata))

    def predict(
        self,
        grasps: Sequence[Grasp],
        model: str = "",
        select: NodeChoice = Selection.ALL,
        timeout: float | None = None,
    ) -> Prediction:
        """Displacements for `grasps` by `model` (empty: the server's default, the Kelvinlet unless it runs
        with --regime); refusals raise grpc.RpcError with the server's code and message."""
        message = self._next(grasps, model, select)
        return Prediction.from_message(self._stub.Predict(message, timeout=timeout, metadata=self._metadata))

    def stream(
        self, requests: Iterable[Sequence[Grasp]], model: str = "", select: NodeChoice = Selection.ALL
    ) -> Iterator[Prediction | StreamError]:
        """One answer per set of grasps, in order, over one stream; a refused message is answered with a
        StreamError and the stream goes on."""
        messages = (request(g, model, select, k) for k, g in enumerate(requests, start=1))
        for reply in self._stub.PredictStream(messages, metadata=self._metadata):
            try:
                yield answer(reply)
            except StreamError as refused:
                yield refused

    def close(self) -> None:
        self._channel.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None, tb: TracebackType | None) -> None:
        self.close()
