"""Rewrite a shipped grasp-encoder model's graph in its served form (grasp_served.py) without the run it
was trained in (run directories are not committed): the network is read back from the graph's own
weights, checked to answer as the graph does, traced again in the served form, checked again, and only
then written in place, the manifest's `[provenance] served_form_at` naming the commit that wrote it. The
basis and metrics stay; the answers do not change.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import onnx
import tomli_w
import torch
from onnx import numpy_helper

from .config import load_config
from .errors import TrainingInputError
from .evaluate import read_manifest
from .export import (
    MANIFEST_HEADER,
    compare_with_onnxruntime,
    interaction_outputs,
    trace_interaction_graph,
)
from .grasp_served import served_form
from .reduced import Encoder, InteractionGraph, ReducedNet
from .reduced_train import reduced_net
from .revision import git_commit
from .static_sizes import RELATIVE_TOLERANCE, read_graph

# Requests the graphs are compared on: one to three grasps of one to twelve points, and sets of lone points.
CHECK_REQUESTS = 24
# What the tracer names a Linear weight it transposed into a constant of its own.
UNNAMED_WEIGHT = "onnx::MatMul_"


def reform(directory: Path) -> str:
    """Rewrites `directory`'s graph in the served form; says what changed."""
    config_path, graph_path = directory / "config.toml", directory / "model.onnx"
    config = load_config(config_path)
    if not (config.architecture == "pod" and config.encoder == "grasps" and config.form == "basis"):
        raise TrainingInputError(
            config_path, "only POD networks of grasp encoders with a basis file have a served form: export it again"
        )
    old = read_graph(graph_path)
    if batch_is_fixed(old):
        return f"{directory}: already in the served form"
    if config.interaction_geometry:
        # Graphs have been exported in the served form since before they could read surface geometry.
        raise TrainingInputError(config_path, "reads surface geometry but is not in the served form: export it again")
    net = reduced_net(config)
    load_graph_weights(net, old, graph_path)
    net.eval()
    trained = InteractionGraph(net, None, torch.zeros(0, 3), False)
    outputs = interaction_outputs(trained)
    requests = check_requests(net.members[0])
    read_back = max(compare_with_onnxruntime(trained, graph_path, requests, "interaction", outputs))
    if read_back > RELATIVE_TOLERANCE:
        raise TrainingInputError(
            graph_path,
            f"the network read back from its weights answers {read_back:.2e} (relative) differently: left as is",
        )
    with tempfile.TemporaryDirectory() as tmp:
        rewritten = Path(tmp) / "model.onnx"
        trace_interaction_graph(
            InteractionGraph(net, None, torch.zeros(0, 3), False, served_form(net)), requests[0], rewritten
        )
        difference = max(compare_with_onnxruntime(trained, rewritten, requests, "interaction", outputs))
        if difference > RELATIVE_TOLERANCE:
            raise TrainingInputError(
                graph_path, f"in the served form it answers {difference:.2e} (relative) differently: left as is"
            )
        before, after = len(old.graph.node), len(read_graph(rewritten).graph.node)
        manifest = read_manifest(directory)
        manifest.setdefault("provenance", {})["served_form_at"] = git_commit()
        rewritten.replace(graph_path)
    (directory / "manifest.toml").write_text(MANIFEST_HEADER + tomli_w.dumps(manifest))
    return (
        f"{directory}: served form, {before} → {after} operators, answers as before "
        f"({difference:.1e} relative on {len(requests)} requests)"
    )


def batch_is_fixed(model: onnx.ModelProto) -> bool:
    """A served-form graph's input is [1, K, 6]; an older graph's batch axis is symbolic."""
    first = model.graph.input[0].type.tensor_type.shape.dim[0]
    return first.HasField("dim_value") and first.dim_value == 1


def load_graph_weights(net: ReducedNet, model: onnx.ModelProto, origin: Path) -> None:
    """Fills `net` from the weights of a graph traced from a network of its configuration: named weights
    by name; the Linear weights the tracer transposed into constants of its own, in the order traced
    (the network's); the normalization from the input's Sub and Div constants; statistics the tracer
    kept once for all members from the one it kept. `reform` checks the result answers as the graph."""
    values = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    shift, scale = normalization(model, values, origin)
    unnamed = sorted(
        (name for name, v in values.items() if name.startswith(UNNAMED_WEIGHT) and v.ndim == 2),
        key=lambda name: int(name[len(UNNAMED_WEIGHT) :]),
    )
    derived = {"x_mean": shift[:3], "x_std": scale[:3], "u_scale": scale[3:]}
    state: dict[str, torch.Tensor] = {}
    for key, tensor in net.state_dict().items():
        base = key.rsplit(".", 1)[-1]
        if f"net.{key}" in values:
            value = values[f"net.{key}"]
        elif base == "weight":
            if not unnamed:
                raise TrainingInputError(origin, f"no weight in the graph for {key}: is it this configuration's?")
            value = values[unnamed.pop(0)].T
        elif base in derived:
            value = derived[base]
        else:
            kept = [name for name in values if name.endswith(f".{base}")]
            if len(kept) != 1:
                raise TrainingInputError(origin, f"no single value in the graph for {key} (found {kept})")
            value = values[kept[0]]
        if tuple(value.shape) != tuple(tensor.shape):
            raise TrainingInputError(
                origin, f"{key} is {list(value.shape)} in the graph, {list(tensor.shape)} in its configuration"
            )
        state[key] = torch.from_numpy(np.array(value))
    if unnamed:
        raise TrainingInputError(origin, f"{len(unnamed)} weights of the graph are not the configuration's network's")
    net.load_state_dict(state)


def normalization(model: onnx.ModelProto, values: dict[str, np.ndarray], origin: Path) -> tuple[np.ndarray, np.ndarray]:
    """The [6] shift and scale the input is normalized by: the constants of the Sub that reads it and of the
    Div that reads that Sub."""
    sub = next((n for n in model.graph.node if n.op_type == "Sub" and n.input[0] == "interaction"), None)
    div = next((n for n in model.graph.node if sub and n.op_type == "Div" and n.input[0] == sub.output[0]), None)
    if sub is None or div is None or sub.input[1] not in values or div.input[1] not in values:
        raise TrainingInputError(origin, "no normalization of the input (Sub, then Div, by constants) in the graph")
    return values[sub.input[1]], values[div.input[1]]


def check_requests(encoder: Encoder) -> list[torch.Tensor]:
    """Requests [1, K, 6] spread as the encoder's training inputs were (its statistics): one to three
    grasps of one to twelve points each, and every fourth a set of points that each move alone."""
    rng = torch.Generator().manual_seed(0)
    requests = []
    for i in range(CHECK_REQUESTS):
        sizes = torch.randint(1, 13, (1 + i % 3,), generator=rng)
        lone = i % 4 == 3
        grasp_of = torch.arange(int(sizes.sum())) if lone else torch.repeat_interleave(torch.arange(len(sizes)), sizes)
        moves = torch.randn(int(grasp_of.max()) + 1, 3, generator=rng) * encoder.u_scale
        points = encoder.x_mean + 0.5 * encoder.x_std * torch.randn(len(grasp_of), 3, generator=rng)
        requests.append(torch.cat([points, moves[grasp_of]], dim=-1)[None].float())
    return requests
