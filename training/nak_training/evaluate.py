"""Score an exported model the way a user meets it: `nak eval` through the serving engine, on the
dataset's test split. The figures (both DCM forms per subset, engine time per request) go into the
manifest's [metrics]; nothing here is computed by PyTorch.
"""

from __future__ import annotations

import json
import subprocess
import tempfile
import tomllib
from pathlib import Path
from typing import Any

import tomli_w

from .errors import TrainingInputError
from .export import MANIFEST_HEADER


def nak_eval(
    nak: Path, data: Path, model: str, mesh: Path, models_root: Path | None, split: str = "test"
) -> dict[str, Any]:
    """Runs `nak eval` and returns its JSON report."""
    if not nak.is_file():
        raise TrainingInputError(nak, "nak binary not found: build it with `cargo build --release` (or pass --nak)")
    with tempfile.TemporaryDirectory() as tmp:
        output = Path(tmp) / "eval.json"
        command = [str(nak), "eval", "--data", str(data), "--model", model, "--mesh", str(mesh)]
        command += ["--split", split, "--output", str(output)]
        if models_root is not None:
            command += ["--models", str(models_root)]
        result = subprocess.run(command, capture_output=True, text=True)
        if result.returncode != 0:
            raise TrainingInputError(" ".join(command), f"nak eval failed:\n{result.stderr.strip()}")
        print(result.stdout, end="")
        report: dict[str, Any] = json.loads(output.read_text())
        return report


def metrics_of(report: dict[str, Any]) -> dict[str, Any]:
    """The flat [metrics] table of a manifest from a `nak eval` report."""
    metrics: dict[str, Any] = {"split": report["split"]}
    for subset, s in report["subsets"].items():
        metrics[f"dcm_{subset}"] = round(s["dcm"], 3)
        metrics[f"dcm_nodal_{subset}"] = round(s["dcm_nodal"], 3)
        metrics[f"dcm_code_{subset}"] = round(s["dcm_code"], 3)
        metrics[f"samples_{subset}"] = s["samples"]
    latency = report.get("latency_us")
    if latency:
        for stage in ("total", "prior", "network"):
            metrics[f"{stage}_ms_p50"] = round(latency[stage]["p50"] / 1e3, 4)
        metrics["total_ms_p90"] = round(latency["total"]["p90"] / 1e3, 4)
        metrics["timed_requests"] = latency["requests"]
        metrics["timed_with_threads"] = report.get("threads", 0)
    return metrics


def evaluate(model_dir: Path, data: Path, nak: Path, mesh: Path) -> dict[str, Any]:
    """Scores the model in `model_dir` and writes its [metrics]; returns them."""
    manifest_path = model_dir / "manifest.toml"
    try:
        manifest = tomllib.loads(manifest_path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise TrainingInputError(manifest_path, f"unreadable manifest ({e})") from e
    name = manifest["model"]["name"]
    # nak loads every model under --models: give it a directory holding only this one.
    with tempfile.TemporaryDirectory() as alone:
        (Path(alone) / model_dir.name).symlink_to(model_dir.resolve(), target_is_directory=True)
        report = nak_eval(nak, data, name, mesh, Path(alone))
    metrics = {"val_dcm": manifest.get("metrics", {}).get("val_dcm"), **metrics_of(report)}
    written = {k: v for k, v in metrics.items() if v is not None}
    manifest["metrics"] = written
    manifest_path.write_text(MANIFEST_HEADER + tomli_w.dumps(manifest))
    return written
