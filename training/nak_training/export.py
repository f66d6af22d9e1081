"""Export a trained network to a nak model directory (DESIGN.md §7): `model.onnx`, `manifest.toml` and
the `config.toml` it was trained with. The graph is checked against PyTorch with onnxruntime before the
manifest is written, so a directory with a manifest always holds a graph that computes the network.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime
import tomli_w
import torch

from .config import TrainConfig
from .dataset import Dataset
from .errors import TrainingInputError
from .train import load_trained, served_features

OPSET = 17
RELATIVE_TOLERANCE = 1e-5
CHECK_SAMPLES = 4
MANIFEST_HEADER = (
    "# Written by `python -m nak_training export` (training/); [metrics] by `... evaluate`, through nak eval.\n"
)


def export(config: TrainConfig, dataset: Dataset, run_dir: Path, out_root: Path, log: Any = print) -> Path:
    model = load_trained(run_dir, config)
    state = json.loads((run_dir / "state.json").read_text())
    summary_path = run_dir / "summary.json"
    if not summary_path.is_file():
        raise TrainingInputError(summary_path, "missing: the run has not finished (train it to the end first)")
    summary = json.loads(summary_path.read_text())
    directory = out_root / config.name
    directory.mkdir(parents=True, exist_ok=True)
    for stale in ("manifest.toml", "model.onnx"):
        (directory / stale).unlink(missing_ok=True)
    check = dataset.load("val", config.subsets).samples[:CHECK_SAMPLES]
    features = served_features(dataset.mesh, [s.nodes for s in check], [s.displacements for s in check])
    with tempfile.TemporaryDirectory() as tmp:
        graph = Path(tmp) / "model.onnx"
        torch.onnx.export(
            model,
            (features[:1],),
            str(graph),
            input_names=["features"],
            output_names=["displacement"],
            opset_version=OPSET,
            dynamo=False,
        )
        difference = compare_with_onnxruntime(model, graph, features)
        log(f"onnxruntime vs PyTorch on {len(check)} val samples: relative difference {difference:.2e}")
        if difference > RELATIVE_TOLERANCE:
            raise TrainingInputError(graph, f"the exported graph differs from PyTorch by {difference:.2e} (relative)")
        graph.replace(directory / "model.onnx")
    (directory / "config.toml").write_text(tomli_w.dumps(config.to_dict()))
    manifest = {
        "model": {
            "name": config.name,
            "mode": config.mode,
            "method": config.method,
            "regime": dataset.regime,
            "inputs": ["position", "displacement", "active"],
            "description": config.description or describe(config),
        },
        "mesh": {
            "name": dataset.mesh.name,
            "content_hash": dataset.mesh.content_hash,
            "node_count": dataset.mesh.node_count,
        },
        "prior": {
            "poisson_ratio": dataset.mesh.prior[0],
            "epsilon_m": float(state["epsilon"]),
            "lambda": dataset.mesh.prior[2],
        },
        "metrics": {"val_dcm": round(float(summary["val_dcm"]), 3)},
        "provenance": provenance(config, dataset, summary, state),
    }
    (directory / "manifest.toml").write_text(MANIFEST_HEADER + tomli_w.dumps(manifest))
    size = (directory / "model.onnx").stat().st_size
    log(f"exported {directory} ({size / 1e6:.2f} MB)")
    return directory


def describe(config: TrainConfig) -> str:
    method = {"base": "Base", "res": "+Res (Kelvinlet residual)", "reg": "+Reg (Kelvinlet regularization)"}
    trained_on = {"single": "single-grasper", "multi": "two-grasper", "all": "all"}[config.subset]
    return f"{config.architecture} ({config.size} size), {method[config.method]}, trained on {trained_on} samples"


def compare_with_onnxruntime(model: torch.nn.Module, graph: Path, features: torch.Tensor) -> float:
    """Largest relative difference (over samples, by the field's norm) between PyTorch and onnxruntime."""
    session = onnxruntime.InferenceSession(str(graph), providers=["CPUExecutionProvider"])
    worst = 0.0
    with torch.no_grad():
        for i in range(features.shape[0]):
            expected = model(features[i : i + 1]).numpy()
            (got,) = session.run(["displacement"], {"features": features[i : i + 1].numpy()})
            scale = max(float(np.linalg.norm(expected)), 1e-30)
            worst = max(worst, float(np.linalg.norm(got - expected)) / scale)
    return worst


def provenance(config: TrainConfig, dataset: Dataset, summary: dict[str, Any], state: dict[str, Any]) -> dict[str, Any]:
    scores = state.get("epsilon_scores", {})
    return {
        "config": "config.toml",
        "architecture": config.architecture,
        "size": config.size,
        "trained_on": config.subset,
        "dataset": str(dataset.root),
        "dataset_seed": dataset.seed,
        "dataset_single": int(dataset.info["single"]),
        "dataset_multi": int(dataset.info["multi"]),
        "train_samples": int(summary["train_samples"]),
        "val_samples": int(summary["val_samples"]),
        "steps": int(summary["steps"]),
        "parameters": int(summary["parameters"]),
        "training_time_s": float(summary["training_time_s"]),
        "epsilon_fit": ", ".join(f"{k} m: {v:.2f} %" for k, v in scores.items()) or "fixed by the config",
        "commit": git_commit(),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "machine": machine(),
        "torch": torch.__version__,
    }


def git_commit() -> str:
    """HEAD, marked dirty when the training package or its configurations differ from it."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "training"], capture_output=True, text=True)
        return head + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, {platform.system()}"
