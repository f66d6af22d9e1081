"""Channel settings shared by the sync and asyncio clients: transport security, the bearer token, and
HTTP/2 settings for full-field answers."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import grpc

from ._generated import deformation_pb2 as pb
from ._types import Grasp, NodeChoice, request

# A full field is ~116 kB: the largest HTTP/2 frame carries it in one DATA frame instead of eight.
CHANNEL_OPTIONS: Sequence[tuple[str, int]] = (
    ("grpc.http2.max_frame_size", 16_777_215),
    ("grpc.max_receive_message_length", 256 << 20),
    ("grpc.max_send_message_length", 16 << 20),
)


@dataclass(frozen=True)
class Security:
    """How to reach a server that uses TLS and/or a bearer token (`nak serve --tls-cert … --auth-token-file …`).

    tls: use TLS (implied by any certificate below). ca: PEM bundle the server's certificate must chain to
    (default: the system's roots). cert/key: this client's certificate and key, for servers that require
    one. server_name: the name to verify the certificate against, when it is not the target's host.
    token / token_file: the bearer token sent with every call.
    """

    tls: bool = False
    ca: Path | None = None
    cert: Path | None = None
    key: Path | None = None
    server_name: str | None = None
    token: str | None = None
    token_file: Path | None = None

    def uses_tls(self) -> bool:
        return self.tls or self.ca is not None or self.cert is not None

    def metadata(self) -> tuple[tuple[str, str], ...]:
        token = self.token
        if self.token_file is not None:
            token = Path(self.token_file).read_text().strip()
            if not token:
                raise ValueError(f"the bearer token file {self.token_file} is empty")
        return (("authorization", f"Bearer {token}"),) if token else ()

    def credentials(self) -> grpc.ChannelCredentials:
        if (self.cert is None) != (self.key is None):
            raise ValueError("a client certificate needs both cert and key")

        def read(path: Path | None) -> bytes | None:
            return None if path is None else Path(path).read_bytes()

        return grpc.ssl_channel_credentials(
            root_certificates=read(self.ca), private_key=read(self.key), certificate_chain=read(self.cert)
        )

    def options(self) -> list[tuple[str, int | str]]:
        options: list[tuple[str, int | str]] = list(CHANNEL_OPTIONS)
        if self.server_name is not None:
            options.append(("grpc.ssl_target_name_override", self.server_name))
        return options


class Session:
    """What the sync and asyncio clients share: the credentials sent with each call and the sequence
    numbers of requests."""

    def __init__(self, security: Security | None) -> None:
        self.security = security or Security()
        self._metadata = self.security.metadata()
        self._sequence = 0

    def _next(self, grasps: Sequence[Grasp], model: str, select: NodeChoice) -> pb.PredictRequest:
        self._sequence += 1
        return request(grasps, model, select, self._sequence)
