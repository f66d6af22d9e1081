"""The asyncio client: the same calls as `Client`, awaited."""

from __future__ import annotations

from collections.abc import AsyncIterable, AsyncIterator, Iterable, Sequence
from types import TracebackType

import grpc

from ._channel import Security, Session
from ._generated import deformation_pb2 as pb
from ._generated import deformation_pb2_grpc as rpc
from ._types import Grasp, Mesh, ModelInfo, NodeChoice, Prediction, Selection, Status, StreamError, answer, request


class AsyncClient(Session):
    """A connection to one nak server for asyncio code. Use as an async context manager, or `await close()`."""

    def __init__(self, target: str = "127.0.0.1:50051", security: Security | None = None) -> None:
        super().__init__(security)
        security, options = self.security, self.security.options()
        if security.uses_tls():
            self._channel = grpc.aio.secure_channel(target, security.credentials(), options)
        else:
            self._channel = grpc.aio.insecure_channel(target, options)
        self._stub = rpc.DeformationStub(self._channel)  # type: ignore[no-untyped-call]

    async def mesh(self, name: str = "") -> Mesh:
        return Mesh.from_message(await self._stub.GetMesh(pb.GetMeshRequest(mesh=name), metadata=self._metadata))

    async def models(self) -> list[ModelInfo]:
        reply = await self._stub.ListModels(pb.ListModelsRequest(), metadata=self._metadata)
        return [ModelInfo.from_message(m) for m in reply.models]

    async def status(self) -> Status:
        return Status.from_message(await self._stub.GetStatus(pb.GetStatusRequest(), metadata=self._metadata))

    async def predict(
        self,
        grasps: Sequence[Grasp],
        model: str = "",
        select: NodeChoice = Selection.ALL,
        timeout: float | None = None,
    ) -> Prediction:
        """Displacements for `grasps` by `model` (empty: the server's default, the Kelvinlet unless it runs
        with --regime); refusals raise grpc.aio.AioRpcError with the server's code and message."""
        message = self._next(grasps, model, select)
        reply = await self._stub.Predict(message, timeout=timeout, metadata=self._metadata)
        return Prediction.from_message(reply)

    async def stream(
        self,
        requests: AsyncIterable[Sequence[Grasp]] | Iterable[Sequence[Grasp]],
        model: str = "",
        select: NodeChoice = Selection.ALL,
    ) -> AsyncIterator[Prediction | StreamError]:
        """One answer per set of grasps, in order, over one stream; a refused message is answered with a
        StreamError and the stream goes on."""

        async def messages() -> AsyncIterator[pb.PredictRequest]:
            sequence = 0
            if isinstance(requests, AsyncIterable):
                async for grasps in requests:
                    sequence += 1
                    yield request(grasps, model, select, sequence)
            else:
                for grasps in requests:
                    sequence += 1
                    yield request(grasps, model, select, sequence)

        async for reply in self._stub.PredictStream(messages(), metadata=self._metadata):
            try:
                yield answer(reply)
            except StreamError as refused:
                yield refused

    async def close(self) -> None:
        await self._channel.close()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, error: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()
