"""Fold the sizes a traced graph reads at run time but that never change.

PyTorch's tracer records every `tensor.shape[i]` as Shape → Gather, even of an axis whose size is
fixed, and what follows from it (a slice of a weight by a width, a reshape to [modes, 3]) is then
computed anew at every request: ONNX Runtime folds constants at load, but not a Shape of a tensor
whose other axes (batch, points) are dynamic. Here each Gather of a Shape whose gathered axes are all
fixed (by ONNX shape inference) becomes a constant, so ONNX Runtime folds the rest at load: on a
three-member grasp encoder about a quarter of the operators a request runs, and their time, go.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import onnxruntime
from google.protobuf.message import DecodeError
from onnx import helper, numpy_helper

from .errors import TrainingInputError

# How far a folded graph may answer from the graph it was folded from (as export checks PyTorch's).
RELATIVE_TOLERANCE = 1e-5


def fold_static_sizes(model: onnx.ModelProto) -> int:
    """Replace in `model` every Gather of a Shape that selects fixed sizes by a constant and drop what
    no longer feeds the outputs; returns how many sizes were folded."""
    graph = model.graph
    sizes = fixed_sizes(model)
    # The tensors a Gather's indices may be, converted only when one is (the weights are not).
    constants = {t.name: t for t in graph.initializer}
    for node in graph.node:
        if node.op_type == "Constant" and node.attribute and node.attribute[0].name == "value":
            constants[node.output[0]] = node.attribute[0].t
    shape_of = {n.output[0]: n for n in graph.node if n.op_type == "Shape"}
    folded = 0
    for i, node in enumerate(graph.node):
        if node.op_type != "Gather" or node.input[0] not in shape_of or node.input[1] not in constants:
            continue
        shape = shape_of[node.input[0]]
        dims = sizes.get(shape.input[0])
        if dims is None:
            continue
        dims = dims[shape_slice(shape, len(dims))]
        picked = np.take(np.array(dims, dtype=object), numpy_helper.to_array(constants[node.input[1]]))
        if any(d is None for d in np.ravel(picked)):
            continue
        value = numpy_helper.from_array(np.array(picked, dtype=np.int64))
        graph.node[i].CopyFrom(helper.make_node("Constant", [], [node.output[0]], name=node.name, value=value))
        folded += 1
    drop_unused(graph)
    return folded


def fixed_sizes(model: onnx.ModelProto) -> dict[str, list[int | None]]:
    """Each value's sizes per axis as shape inference knows them (None: dynamic)."""
    inferred = onnx.shape_inference.infer_shapes(model)
    out: dict[str, list[int | None]] = {}
    for value in [*inferred.graph.value_info, *inferred.graph.input, *inferred.graph.output]:
        tensor = value.type.tensor_type
        if tensor.HasField("shape"):
            out[value.name] = [d.dim_value if d.HasField("dim_value") else None for d in tensor.shape.dim]
    return out


def shape_slice(shape: onnx.NodeProto, rank: int) -> slice:
    """The axes a Shape node returns (its `start` and `end`, opset 15 on)."""
    bounds = {a.name: helper.get_attribute_value(a) for a in shape.attribute}
    return slice(bounds.get("start", 0), bounds.get("end", rank))


def drop_unused(graph: onnx.GraphProto) -> None:
    """Remove nodes none of whose outputs is read, until none is left."""
    outputs = {o.name for o in graph.output}
    while True:
        read = {name for n in graph.node for name in n.input} | outputs
        unused = [n for n in graph.node if not any(o in read for o in n.output)]
        if not unused:
            return
        for node in unused:
            graph.node.remove(node)


def fold_file(path: Path) -> int:
    """`fold_static_sizes` on the graph at `path`, in place; how many sizes it folded."""
    model = read_graph(path)
    folded = fold_static_sizes(model)
    if folded:
        onnx.checker.check_model(model)
        onnx.save(model, str(path))
    return folded


def read_graph(path: Path) -> onnx.ModelProto:
    try:
        return onnx.load(str(path))
    except (OSError, DecodeError) as e:
        raise TrainingInputError(path, f"unreadable ONNX graph ({e})") from e


def refold_interaction_graph(directory: Path) -> str:
    """Fold the sizes of a model directory's interaction-form graph exported before export did it,
    written back only if it answers as before (random requests of 1 to 16 points, RELATIVE_TOLERANCE)."""
    path = directory / "model.onnx"
    model = read_graph(path)
    if [i.name for i in model.graph.input] != ["interaction"]:
        raise TrainingInputError(path, "not an interaction-form graph (a reduced network): export it again instead")
    as_it_was = model.SerializeToString()
    folded = fold_static_sizes(model)
    if not folded:
        return f"{directory}: nothing to fold"
    onnx.checker.check_model(model)
    rng = np.random.default_rng(0)
    before = onnxruntime.InferenceSession(as_it_was, providers=["CPUExecutionProvider"])
    after = onnxruntime.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    for points in (1, 4, 9, 16):
        x = np.concatenate([rng.random((2, points, 3)) * 0.1, rng.normal(size=(2, points, 3)) * 0.01], axis=-1)
        x = x.astype(np.float32)
        for old, new in zip(before.run(None, {"interaction": x}), after.run(None, {"interaction": x}), strict=True):
            difference = float(np.linalg.norm(new - old) / max(float(np.linalg.norm(old)), 1e-30))
            if difference > RELATIVE_TOLERANCE:
                raise TrainingInputError(
                    path, f"folded, it answers {difference:.2e} (relative) differently: left as is"
                )
    onnx.save(model, str(path))
    return f"{directory}: {folded} sizes folded, answers unchanged"
