"""Served networks agree with an independent evaluation of the same .onnx files by onnxruntime in Python."""

from __future__ import annotations

import json
import subprocess
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import client
import grpc
import numpy as np
import onnxruntime
import pytest
from conftest import ROOT, start_server

MODELS = ROOT / "tests" / "models" / "phantom-liver-coarse"


@pytest.fixture(scope="module")
def coarse_server(nak_binary: Path) -> Iterator[str]:
    args = ["--mesh", str(ROOT / "models/phantom-liver/liver-coarse.msh"), "--models", str(MODELS)]
    with start_server(nak_binary, args) as address:
        yield address


def manifest(name: str) -> dict[str, Any]:
    with open(MODELS / name / "manifest.toml", "rb") as f:
        return tomllib.load(f)


@pytest.mark.parametrize("name", ["mlp-residual", "mlp-direct-prior", "pointnet-residual", "pointnet-direct"])
def test_served_field_matches_onnxruntime(coarse_server: str, name: str) -> None:
    pb, rpc = client.load_stubs()
    with grpc.insecure_channel(coarse_server) as channel:
        stub = rpc.DeformationStub(channel)
        mesh = stub.GetMesh(pb.GetMeshRequest())
        positions = np.frombuffer(mesh.positions, dtype="<f4").reshape(-1, 3)
        sets = {s.name: list(s.nodes) for s in mesh.node_sets}
        grasps = [
            pb.Grasp(nodes=sets["grasp_03"][:10], displacement=pb.Vec3(x=0.01, y=0.03, z=-0.01)),
            pb.Grasp(nodes=sets["grasp_08"][:10], displacement=pb.Vec3(x=-0.02, y=0.02, z=0.015)),
        ]

        def field(model: str) -> np.ndarray:
            response = stub.Predict(pb.PredictRequest(model=model, grasps=grasps))
            return np.frombuffer(response.displacements, dtype="<f4").reshape(-1, 3)

        served, prior = field(name), field("kelvinlet")

    info = manifest(name)["model"]
    n = len(positions)
    features = np.zeros((1, n, 10 if "prior" in info["inputs"] else 7), dtype=np.float32)
    features[0, :, 0:3] = positions
    for g in grasps:
        for node in g.nodes:
            features[0, node, 3:6] = (g.displacement.x, g.displacement.y, g.displacement.z)
            features[0, node, 6] = 1.0
    if "prior" in info["inputs"]:
        features[0, :, 7:10] = prior
    session = onnxruntime.InferenceSession(str(MODELS / name / "model.onnx"), providers=["CPUExecutionProvider"])
    (network,) = session.run(["displacement"], {"features": features})
    expected = network[0] + (prior if info["mode"] == "residual" else 0.0)
    for g in grasps:  # held nodes answer the grasp (docs/design.md §7)
        expected[list(g.nodes)] = (g.displacement.x, g.displacement.y, g.displacement.z)
    relative = np.linalg.norm(served - expected) / np.linalg.norm(expected)
    assert relative < 1e-5, f"{name}: relative difference {relative:.2e}"


def test_serving_models_without_onnxruntime_names_what_is_missing(nak_binary: Path, tmp_path: Path) -> None:
    result = subprocess.run(
        [
            str(nak_binary),
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--mesh",
            str(ROOT / "models/phantom-liver/liver-coarse.msh"),
            "--models",
            str(MODELS),
        ],
        env={"PATH": "/usr/bin:/bin", "RUST_BACKTRACE": "0"},
        cwd=tmp_path,  # away from the checkout's .venv, where nak would find ONNX Runtime by itself
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode != 0
    assert "ORT_DYLIB_PATH" in result.stderr and "onnxruntime==1.31.1" in result.stderr, result.stderr
    assert "scripts/setup-python" in result.stderr, result.stderr


SHIPPED = sorted(p.parent.name for p in (ROOT / "models" / "phantom-liver").glob("*/manifest.toml"))


def test_the_embedded_phantom_serves_its_shipped_networks(nak_server: str) -> None:
    pb, rpc = client.load_stubs()
    with grpc.insecure_channel(nak_server) as channel:
        stub = rpc.DeformationStub(channel)
        listed = {m.name: dict(m.metadata) for m in stub.ListModels(pb.ListModelsRequest()).models}
        assert set(SHIPPED) <= set(listed), (SHIPPED, sorted(listed))
        sets = {s.name: list(s.nodes) for s in stub.GetMesh(pb.GetMeshRequest()).node_sets}
        for name in SHIPPED:
            with open(ROOT / "models" / "phantom-liver" / name / "manifest.toml", "rb") as f:
                manifest = tomllib.load(f)
            assert listed[name]["method"] == manifest["model"]["method"]
            assert float(listed[name]["prior.epsilon_m"]) == manifest["prior"]["epsilon_m"]
            grasp = pb.Grasp(nodes=sets["grasp_04"][:6], displacement=pb.Vec3(y=0.02))
            response = stub.Predict(pb.PredictRequest(model=name, grasps=[grasp]))
            u = np.frombuffer(response.displacements, dtype="<f4").reshape(-1, 3)
            assert np.isfinite(u).all() and response.timing.network_us > 0, name
            assert np.abs(u).max() > 1e-3, f"{name} does not move the tissue"


def test_without_onnxruntime_the_embedded_phantom_still_serves_the_prior(nak_binary: Path, tmp_path: Path) -> None:
    if not SHIPPED:
        pytest.skip("no shipped networks")
    proc = subprocess.Popen(
        [str(nak_binary), "serve", "--listen", "127.0.0.1:0", "--log-format", "json"],
        env={"PATH": "/usr/bin:/bin"},
        cwd=tmp_path,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stderr is not None
    warning = ""
    try:
        for line in proc.stderr:
            message = json.loads(line)["fields"].get("message", "")
            if "shipped networks" in message:
                warning = message
            if message == "listening":
                break
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    assert all(name in warning for name in SHIPPED) and "scripts/setup-python" in warning, warning
