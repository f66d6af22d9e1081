"""Score an exported model the way a user meets it: `nak eval` through the serving engine, on the
dataset's test split. The figures (both DCM forms per subset, engine time per request) go into the
manifest's [metrics]; nothing here is computed by PyTorch.
"""

from __future__ import annotations

import dataclasses
import json
import tempfile
import tomllib
from pathlib import Path
from typing import Any

import tomli_w

from .config import TrainConfig
from .dataset import Dataset, read_json
from .errors import TrainingInputError
from .export import CEILING_PREFIX, MANIFEST_HEADER, export
from .served import Nak


def nak_eval(
    nak: Path,
    data: Path,
    model: str,
    mesh: Path,
    models_root: Path | None,
    split: str = "test",
    flags: tuple[str, ...] = (),
) -> dict[str, Any]:
    """Runs `nak eval` (with `flags`, e.g. `--green-tangent`) and returns its JSON report."""
    with tempfile.TemporaryDirectory() as tmp:
        output = Path(tmp) / "eval.json"
        args = ["eval", "--data", str(data), "--model", model, "--split", split, "--output", str(output), *flags]
        if models_root is not None:
            args += ["--models", str(models_root)]
        print(Nak(nak, mesh).run(*args), end="")
        report: dict[str, Any] = json.loads(output.read_text())
        return report


def metrics_of(report: dict[str, Any]) -> dict[str, Any]:
    """The flat [metrics] table of a manifest from a `nak eval` report."""
    # How the served field answered the held nodes (absent from reports before nak prescribed them).
    metrics: dict[str, Any] = {
        "split": report["split"],
        "scored_on_seed": report.get("seed"),
        "held_nodes": report.get("held_nodes"),
    }
    for subset, s in report["subsets"].items():
        metrics[f"dcm_{subset}"] = round(s["dcm"], 3)
        if s.get("dcm_standard_error") is not None:
            metrics[f"dcm_se_{subset}"] = round(s["dcm_standard_error"], 3)
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


def force_metrics_of(report: dict[str, Any]) -> dict[str, Any]:
    """The test error of a model's grasp forces, per subset, from a `nak eval` report (empty when the
    model or the data has no forces)."""
    metrics: dict[str, Any] = {}
    for subset, s in report.get("grasp_forces", {}).items():
        metrics[f"mean_relative_error_{subset}"] = round(s["mean_relative_error"], 4)
        metrics[f"median_relative_error_{subset}"] = round(s["median_relative_error"], 4)
        metrics[f"median_magnitude_ratio_{subset}"] = round(s["median_magnitude_ratio"], 4)
        metrics[f"median_angle_deg_{subset}"] = round(s["median_angle_deg"], 2)
        metrics[f"grasps_{subset}"] = s["grasps"]
    return metrics


def read_manifest(model_dir: Path) -> dict[str, Any]:
    """The model directory's manifest.toml, refused with its path when unreadable."""
    manifest_path = model_dir / "manifest.toml"
    try:
        return tomllib.loads(manifest_path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise TrainingInputError(manifest_path, f"unreadable manifest ({e})") from e


def eval_model_dir(
    model_dir: Path, name: str, data: Path, nak: Path, mesh: Path, split: str, flags: tuple[str, ...] = ()
) -> dict[str, Any]:
    """`nak eval`'s JSON report of the model `name` in `model_dir` on `split` of `data`."""
    # nak loads every model under --models: give it a directory holding only this one.
    with tempfile.TemporaryDirectory() as alone:
        (Path(alone) / model_dir.name).symlink_to(model_dir.resolve(), target_is_directory=True)
        return nak_eval(nak, data, name, mesh, Path(alone), split, flags)


def sample_errors(report: dict[str, Any]) -> list[dict[str, Any]]:
    """The per-sample errors of a `nak eval` JSON report (`--output`), refused when it has none."""
    samples: list[dict[str, Any]] | None = report.get("samples")
    if not samples:
        raise TrainingInputError(Path(str(report.get("data"))), "nak eval reported no per-sample errors")
    return samples


# The models nak serves without a model directory, and the flag each needs.
BUILT_IN = {"kelvinlet": (), "green-linear": ("--green-linear",), "green-tangent": ("--green-tangent",)}
# Errors only: no requests timed after the scoring pass.
UNTIMED = ("--latency-samples", "0")


def scored(model: str, data: Path, nak: Path, mesh: Path, split: str) -> tuple[str, dict[str, Any]]:
    """The model's name and `nak eval`'s report of it on `split` of `data` (errors only, untimed): a
    model directory, or a model nak serves by name."""
    if model in BUILT_IN:
        return model, nak_eval(nak, data, model, mesh, None, split, BUILT_IN[model] + UNTIMED)
    directory = Path(model)
    if not directory.is_dir():
        raise TrainingInputError(directory, f"is not a model directory (nor one of {', '.join(BUILT_IN)})")
    name = read_manifest(directory)["model"]["name"]
    return name, eval_model_dir(directory, name, data, nak, mesh, split, UNTIMED)


def refuse_scoring_on_its_training_set(model_dir: Path, manifest: dict[str, Any], data: Path) -> None:
    """A model is scored on samples it never trained on: not on a set of a seed whose every sample
    trained it (a --more-data set, or its own set under holdout = "val")."""
    provenance = manifest.get("provenance", {})
    trained = {int(more["seed"]) for more in provenance.get("more_data", [])}
    if provenance.get("holdout") == "val":
        trained.add(int(provenance["dataset_seed"]))
    seed = read_json(data / "dataset.json").get("seed")
    if seed in trained:
        raise TrainingInputError(
            model_dir,
            f"trained on the samples of seed {seed}, which {data} holds: score it on a set of a seed it never saw",
        )


def evaluate(model_dir: Path, data: Path, nak: Path, mesh: Path, split: str = "test") -> dict[str, Any]:
    """Scores the model in `model_dir` on `split` of `data` and writes its [metrics] (and, for a model
    with learned forces, their error in [forces]); returns the metrics."""
    manifest = read_manifest(model_dir)
    refuse_scoring_on_its_training_set(model_dir, manifest, data)
    report = eval_model_dir(model_dir, manifest["model"]["name"], data, nak, mesh, split)
    kept = {k: v for k, v in manifest.get("metrics", {}).items() if k == "val_dcm" or k.startswith(CEILING_PREFIX)}
    metrics = {**kept, **metrics_of(report)}
    written = {k: v for k, v in metrics.items() if v is not None}
    manifest["metrics"] = written
    if "forces" in manifest:
        manifest["forces"] = {"mode": manifest["forces"]["mode"], **force_metrics_of(report)}
    (model_dir / "manifest.toml").write_text(MANIFEST_HEADER + tomli_w.dumps(manifest))
    return written


FORMS = (("f32", "basis", "f32"), ("f16", "basis", "f16"), ("graph", "graph", "f32"))


def compare_forms(
    config: TrainConfig, dataset: Dataset, run_dir: Path, out_root: Path, nak: Path, mesh: Path
) -> list[dict[str, Any]]:
    """Exports one trained reduced network in each way its basis can ship (an f32 or f16 basis file
    that nak multiplies, or folded into the graph for ONNX Runtime) and times each through nak eval.
    The DCM must agree (to f16 rounding); the network time says where the product is fastest."""
    if not config.reduced:
        raise TrainingInputError(config.name, "forms compares the shipping forms of a reduced network (pod, deeponet)")
    rows = []
    for suffix, form, precision in FORMS:
        variant = dataclasses.replace(config, name=f"{config.name}-{suffix}", form=form, basis_precision=precision)
        export(variant, dataset, run_dir, out_root, log=lambda _: None)
        metrics = evaluate(out_root / variant.name, dataset.root, nak, mesh)
        rows.append({"form": suffix, **metrics})
    print(f"{'form':<6} {'DCM combined':>12} {'network p50 ms':>15} {'total p50 ms':>13}")
    for r in rows:
        print(f"{r['form']:<6} {r['dcm_combined']:>12.3f} {r['network_ms_p50']:>15.4f} {r['total_ms_p50']:>13.4f}")
    return rows
