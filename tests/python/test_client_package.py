"""The pip-installable client (clients/python, package nak_client) against a real `nak serve`: numpy
answers equal to `nak predict`'s, sync and asyncio alike, streams with refusals in place, and TLS with
a bearer token (certificates made here with openssl)."""

from __future__ import annotations

import asyncio
import json
import subprocess
from pathlib import Path

import grpc
import numpy as np
import pytest
from nak_client import AsyncClient, Client, Grasp, Prediction, Security, Selection, StreamError

from conftest import start_server


def grasps_for(mesh_sets: dict[str, np.ndarray]) -> list[Grasp]:
    return [
        Grasp(nodes=mesh_sets["grasp_04"][:10], displacement=(0.0, 0.02, 0.0)),
        Grasp(point=(0.0, -0.02, 0.05), radius=0.01, displacement=(0.01, 0.0, 0.0)),
    ]


def test_sync_answers_equal_nak_predict(nak_binary: Path, nak_server: str, tmp_path: Path) -> None:
    with Client(nak_server) as nak:
        mesh = nak.mesh()
        assert mesh.positions.shape == (9701, 3) and mesh.positions.dtype == np.float32
        assert {"fixed", "grasp_04"} <= mesh.node_sets.keys()
        models = {m.name: m for m in nak.models()}
        assert models["kelvinlet"].kind == "prior" and models["kelvinlet"].forces == "estimate"
        grasps = grasps_for(mesh.node_sets)
        answer = nak.predict(grasps)
        surface = nak.predict(grasps, select=Selection.SURFACE)
        some = nak.predict(grasps, select=[5, 7, 11])
        assert nak.status().admission["in_flight"] == 0

    spec = [
        {"nodes": [int(n) for n in mesh.node_sets["grasp_04"][:10]], "displacement": [0.0, 0.02, 0.0]},
        {"point": [0.0, -0.02, 0.05], "radius": 0.01, "displacement": [0.01, 0.0, 0.0]},
    ]
    (tmp_path / "grasps.json").write_text(json.dumps({"grasps": spec}))
    subprocess.run(
        [str(nak_binary), "predict", "--grasps", str(tmp_path / "grasps.json"), "--out", str(tmp_path / "u.npy")],
        check=True,
        capture_output=True,
    )
    # The server may split the field over threads differently from the one-shot CLI: f32 sums in another
    # order differ in their last bits (~1e-8 m on fields of centimetres).
    np.testing.assert_allclose(answer.displacements, np.load(tmp_path / "u.npy"), rtol=0, atol=1e-7)
    assert answer.node_ids is None and answer.forces.shape == (2, 3) and answer.timing.total_us > 0
    assert surface.node_ids is not None
    np.testing.assert_array_equal(surface.node_ids, mesh.surface_nodes)
    np.testing.assert_array_equal(surface.displacements, answer.displacements[mesh.surface_nodes])
    np.testing.assert_array_equal(some.displacements, answer.displacements[[5, 7, 11]])


def test_refusals_raise_with_the_servers_code_and_message(nak_server: str) -> None:
    with Client(nak_server) as nak:
        with pytest.raises(grpc.RpcError) as refused:
            nak.predict([Grasp(nodes=[10**7], displacement=(0, 0.01, 0))])
        assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert "10000000" in str(refused.value.details())


def test_asyncio_client_and_streams_answer_in_order_with_refusals_in_place(nak_server: str) -> None:
    async def run() -> tuple[Prediction, list[Prediction | StreamError], Prediction]:
        async with AsyncClient(nak_server) as nak:
            mesh = await nak.mesh()
            grasps = grasps_for(mesh.node_sets)
            single = await nak.predict(grasps)
            bad = [Grasp(nodes=[10**7], displacement=(0, 0.01, 0))]
            streamed = [a async for a in nak.stream([grasps, bad, grasps])]
        with Client(nak_server) as sync:
            return single, streamed, sync.predict(grasps)

    single, streamed, reference = asyncio.run(run())
    np.testing.assert_array_equal(single.displacements, reference.displacements)
    first, refused, third = streamed
    assert isinstance(first, Prediction) and isinstance(third, Prediction)
    np.testing.assert_array_equal(first.displacements, reference.displacements)
    assert isinstance(refused, StreamError) and refused.sequence == 2 and "10000000" in refused.message
    assert third.sequence == 3


def openssl(*args: str) -> None:
    subprocess.run(["openssl", *args], check=True, capture_output=True)


def test_tls_and_a_bearer_token(nak_binary: Path, tmp_path: Path) -> None:
    key, cert = tmp_path / "key.pem", tmp_path / "cert.pem"
    openssl(
        "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-days", "1",
        "-subj", "/CN=localhost", "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1",
        "-keyout", str(key), "-out", str(cert),
    )  # fmt: skip
    token = tmp_path / "token"
    token.write_text("s3cret\n")
    args = ["--tls-cert", str(cert), "--tls-key", str(key), "--auth-token-file", str(token)]
    with start_server(nak_binary, args) as address:
        port = address.rsplit(":", 1)[1]
        with Client(f"localhost:{port}", Security(ca=cert, token_file=token)) as nak:
            assert nak.mesh().name == "phantom-liver"
        with Client(f"localhost:{port}", Security(ca=cert, token="wrong")) as nak:
            with pytest.raises(grpc.RpcError) as refused:
                nak.models()
            assert refused.value.code() == grpc.StatusCode.UNAUTHENTICATED
