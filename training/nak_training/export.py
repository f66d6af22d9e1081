"""Export a trained network to a nak model directory (docs/design.md §7): `model.onnx`, `manifest.toml` and
the `config.toml` it was trained with. The graph is checked against PyTorch with onnxruntime before the
manifest is written, so a directory with a manifest always holds a graph that computes the network.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime
import tomli_w
import torch

from safetensors.numpy import save_file

from .config import TrainConfig
from .dataset import Dataset, Sample
from .errors import TrainingInputError
from .grasp_served import served_form
from .reduced import InteractionGraph
from .reduced_train import basis_ceiling, interaction_input, load_reduced
from .revision import git_commit
from .static_sizes import RELATIVE_TOLERANCE, fold_file
from .train import load_trained, served_features

OPSET = 17
BASIS_FILE = "basis.safetensors"
CEILING_PREFIX = "basis_ceiling_dcm_m"
CHECK_SAMPLES = 4
MANIFEST_HEADER = (
    "# Written by `python -m nak_training export` (training/); [metrics] by `... evaluate`, through nak eval.\n"
)


def export(config: TrainConfig, dataset: Dataset, run_dir: Path, out_root: Path, log: Any = print) -> Path:
    state = json.loads((run_dir / "state.json").read_text())
    summary_path = run_dir / "summary.json"
    if not summary_path.is_file():
        raise TrainingInputError(summary_path, "missing: the run has not finished (train it to the end first)")
    summary = json.loads(summary_path.read_text())
    trained_law = dataset.law_of_run(summary)
    if trained_law != dataset.volumetric_law:
        raise TrainingInputError(
            summary_path,
            f"the run was trained on data solved under the volumetric law {trained_law}; {dataset.root} was "
            f"solved under {dataset.volumetric_law}: export with the dataset it was trained on",
        )
    directory = out_root / config.name
    directory.mkdir(parents=True, exist_ok=True)
    for stale in ("manifest.toml", "model.onnx", BASIS_FILE):
        (directory / stale).unlink(missing_ok=True)
    check = dataset.load("val", config.subsets).samples[:CHECK_SAMPLES]
    with tempfile.TemporaryDirectory() as tmp:
        graph = Path(tmp) / "model.onnx"
        if config.reduced:
            inputs = write_interaction_graph(config, dataset, run_dir, check, graph, directory, log)
        else:
            inputs = write_features_graph(config, dataset, run_dir, check, graph, log)
        graph.replace(directory / "model.onnx")
    (directory / "config.toml").write_text(tomli_w.dumps(config.to_dict()))
    manifest = {
        "model": {
            "name": config.name,
            "mode": config.mode,
            "method": config.method,
            "regime": dataset.regime,
            **({"volumetric_law": dataset.volumetric_law} if dataset.volumetric_law else {}),
            "inputs": inputs,
            "description": config.description or describe(config),
        },
        "mesh": {
            "name": dataset.mesh.name,
            "content_hash": dataset.mesh.content_hash,
            "node_count": dataset.mesh.node_count,
        },
        "prior": {
            "model": config.prior if config.method == "res" else "kelvinlet",
            "poisson_ratio": dataset.mesh.prior[0],
            "epsilon_m": float(state["epsilon"]),
            "lambda": dataset.mesh.prior[2],
        },
        "metrics": {"val_dcm": round(float(summary["val_dcm"]), 3), **ceiling_metrics(config, run_dir)},
        "provenance": provenance(config, dataset, summary, state),
        # The test error of the forces is written by `evaluate`, through nak eval.
        **({"forces": {"mode": config.force_mode}} if config.forces else {}),
    }
    (directory / "manifest.toml").write_text(MANIFEST_HEADER + tomli_w.dumps(manifest))
    size = sum(f.stat().st_size for f in directory.iterdir() if f.name in ("model.onnx", BASIS_FILE))
    log(f"exported {directory} ({size / 1e6:.2f} MB)")
    return directory


def write_features_graph(
    config: TrainConfig, dataset: Dataset, run_dir: Path, check: list[Sample], graph: Path, log: Any
) -> list[str]:
    """A full-field network: `features` [B, N, 7] → `displacement` [B, N, 3]."""
    model = load_trained(run_dir, config, dataset.mesh)
    features = served_features(dataset.mesh, [s.nodes for s in check], [s.displacements for s in check])
    torch.onnx.export(
        model,
        (features[:1],),
        str(graph),
        input_names=["features"],
        output_names=["displacement"],
        opset_version=OPSET,
        dynamo=False,
    )
    fold_file(graph)
    checked(model, graph, [features[i : i + 1] for i in range(len(check))], "features", ["displacement"], log)
    return ["position", "displacement", "active"]


def write_interaction_graph(
    config: TrainConfig, dataset: Dataset, run_dir: Path, check: list[Sample], graph: Path, directory: Path, log: Any
) -> list[str]:
    """A reduced network: `interaction` [B, K, 6] (10 with surface geometry) → `coefficients` [B, M] with `basis.safetensors`
    beside the graph, or → `displacement` [B, N, 3] with the basis folded into it (form = "graph";
    a DeepONet's trunk then stays a subgraph over the node positions that ONNX Runtime folds at load)."""
    net, basis = load_reduced(run_dir, config)
    positions = dataset.mesh.positions
    folded = config.form == "graph"
    if basis is None and not folded:
        assert net.trunk is not None
        with torch.no_grad():
            basis = net.trunk(positions.float()).double()
    trained = InteractionGraph(net, basis if folded else None, positions, folded)
    inputs = [
        interaction_input(
            dataset.mesh,
            torch.from_numpy(s.nodes),
            positions[s.nodes],
            torch.from_numpy(s.displacements),
            config.interaction_geometry,
            config.interaction_depth,
        )[None]
        for s in check
    ]
    outputs = interaction_outputs(trained)
    trace_interaction_graph(
        InteractionGraph(net, basis if folded else None, positions, folded, served_form(net)), inputs[0], graph
    )
    checked(trained, graph, inputs, "interaction", outputs, log)
    if basis is not None and not folded:
        values = basis.float().numpy().astype(np.float16 if config.basis_precision == "f16" else np.float32)
        save_file({"basis": values}, str(directory / BASIS_FILE), metadata={"mesh_hash": dataset.mesh.content_hash})
    return ["interaction"]


def interaction_outputs(module: InteractionGraph) -> list[str]:
    output = "displacement" if module.folded else "coefficients"
    return [output, "forces"] if module.net.forces is not None else [output]


def trace_interaction_graph(module: InteractionGraph, example: torch.Tensor, graph: Path) -> None:
    """Writes `module` to `graph` as ONNX, its fixed sizes folded. A served form answers one request at a
    time: its batch axis is fixed at 1 (nak sends one)."""
    outputs = interaction_outputs(module)
    batch = {} if module.served is not None else {0: "batch"}
    torch.onnx.export(
        module,
        (example,),
        str(graph),
        input_names=["interaction"],
        output_names=outputs,
        dynamic_axes={"interaction": {**batch, 1: "points"}, outputs[0]: batch}
        | ({"forces": {**batch, 1: "points"}} if "forces" in outputs else {}),
        opset_version=OPSET,
        do_constant_folding=module.net.trunk is None,
        dynamo=False,
    )
    fold_file(graph)


def ceiling_metrics(config: TrainConfig, run_dir: Path) -> dict[str, float]:
    """A POD's own ceiling: the test split's DCM of the best M-term approximation of its targets."""
    if config.architecture != "pod":
        return {}
    return {f"{CEILING_PREFIX}{m}": round(v, 3) for m, v in basis_ceiling(run_dir).items()}


def checked(
    model: torch.nn.Module, graph: Path, inputs: list[torch.Tensor], name: str, outputs: list[str], log: Any
) -> None:
    """Refuses a graph any of whose `outputs` differs from PyTorch on `inputs` by more than
    RELATIVE_TOLERANCE."""
    for output, difference in zip(outputs, compare_with_onnxruntime(model, graph, inputs, name, outputs), strict=True):
        log(f"onnxruntime vs PyTorch on {len(inputs)} val samples, {output}: relative difference {difference:.2e}")
        if difference > RELATIVE_TOLERANCE:
            raise TrainingInputError(
                graph, f"the exported graph's {output} differs from PyTorch by {difference:.2e} (relative)"
            )


def describe(config: TrainConfig) -> str:
    residual = "Kelvinlet residual" if config.prior == "kelvinlet" else f"{config.prior} residual"
    method = {"base": "Base", "res": f"+Res ({residual})", "reg": "+Reg (Kelvinlet regularization)"}
    trained_on = {"single": "single-grasper", "multi": "two-grasper", "all": "all"}[config.subset]
    if config.reduced:
        basis = {"pod": "POD basis", "deeponet": "DeepONet trunk"}[config.architecture]
        shipped = f"{config.basis_precision} basis file" if config.form == "basis" else "folded into the graph"
        network = f"{basis}, M = {config.modes} ({shipped}), set encoder width {config.width}"
    else:
        network = f"{config.architecture} ({config.size} size)"
    return f"{network}, {method[config.method]}, trained on {trained_on} samples"


def compare_with_onnxruntime(
    model: torch.nn.Module,
    graph: Path,
    inputs: list[torch.Tensor],
    name: str = "features",
    outputs: list[str] | None = None,
) -> list[float]:
    """Per output (in the model's order), the largest relative difference over `inputs`, by the
    output's norm, between PyTorch and onnxruntime."""
    outputs = outputs or ["displacement"]
    session = onnxruntime.InferenceSession(str(graph), providers=["CPUExecutionProvider"])
    worst = [0.0] * len(outputs)
    with torch.no_grad():
        for x in inputs:
            result = model(x)
            expected = result if isinstance(result, tuple) else (result,)
            got = session.run(outputs, {name: x.numpy()})
            for i, (e, g) in enumerate(zip(expected, got, strict=True)):
                scale = max(float(np.linalg.norm(e.numpy())), 1e-30)
                worst[i] = max(worst[i], float(np.linalg.norm(g - e.numpy())) / scale)
    return worst


def provenance(config: TrainConfig, dataset: Dataset, summary: dict[str, Any], state: dict[str, Any]) -> dict[str, Any]:
    scores = state.get("epsilon_scores", {})
    exported_at = git_commit()
    return {
        "config": "config.toml",
        "architecture": config.architecture,
        "size": config.size,
        "trained_on": config.subset,
        "dataset": str(dataset.root),
        "dataset_seed": dataset.seed,
        "dataset_single": int(dataset.info["single"]),
        "dataset_multi": int(dataset.info["multi"]),
        # "val": every sample of the dataset but its val samples trained it (TrainConfig.holdout).
        "holdout": config.holdout,
        "train_samples": int(summary["train_samples"]),
        # The converged load-step states of the train samples that trained it too (path_states_from).
        **({"path_states": int(summary["path_states"])} if "path_states" in summary else {}),
        "val_samples": int(summary["val_samples"]),
        # Trained while the set was still being made: the chunks it had, to retrain on the same samples.
        **({"dataset_chunks": summary["chunks"]} if "chunks" in summary else {}),
        # Sets of other seeds whose every sample joined the train split.
        **({"more_data": summary["more_data"]} if "more_data" in summary else {}),
        "steps": int(summary["steps"]),
        "parameters": int(summary["parameters"]),
        "training_time_s": float(summary["training_time_s"]),
        "epsilon_fit": ", ".join(f"{k} m: {v:.2f} %" for k, v in scores.items()) or "fixed by the config",
        # The commit the weights were trained at (runs from before it was recorded: the export's).
        "commit": str(summary.get("commit", exported_at)),
        "exported_at": exported_at,
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "machine": machine(),
        "torch": torch.__version__,
    }


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
