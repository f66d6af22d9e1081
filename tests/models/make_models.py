"""Write the small ONNX test models (fixed, seeded weights) that exercise nak's model contract.

docs/design.md §7: input `features` f32 [B, N, C] with channels position (3), prescribed displacement (3),
active flag (1) and, if the manifest lists it, the prior (3); output `displacement` f32 [B, N, 3];
normalization inside the graph. The weights are random, not trained: these models test the serving
machinery, not accuracy.

For each mesh given (default: the phantom at paper scale and the coarse phantom) this writes
tests/models/<mesh>/<model>/{model.onnx, manifest.toml} for:

* mlp-residual       per-node MLP (7 → 64 → 64 → 3), residual on the Kelvinlet prior
* mlp-direct-prior   per-node MLP that also reads the prior channels (10 inputs), direct
* pointnet-residual  PointNet-style (per-node MLP, global max-pool, per-node head), residual
* pointnet-direct    the same, direct

and, for the coarse mesh only, models of the `interaction` form (input [B, K, 6]) over a random basis
of REDUCED_MODES modes:

* reduced-residual       set encoder → `coefficients` [B, M]; basis.safetensors (f32) beside it
* reduced-residual-f16   the same graph and basis, the basis stored in f16
* reduced-folded         the same encoder with the basis folded into the graph: `displacement`
* reduced-forces         reduced-residual with a second output `forces` [B, K, 3] = FORCE_GAINS ⊙ u_k,
                         a closed form the tests check nak's per-grasp sums against
* reduced-geometry       input [B, K, 10] (each point's surface normal and nodal volume after its position
                         and displacement), `forces` = GEOMETRY_GAIN · V_k n_k: what nak fed it, per grasp

(the three give the same field, up to f16 rounding), and tests/models/faulty/<case>/ models that must
be refused, fail, or run long.
Run from the repository root after `cargo build`: python tests/models/make_models.py
"""

from __future__ import annotations

import argparse
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper
from safetensors.numpy import save_file

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
OPSET = 17
WIDTH = 64
BASE_CHANNELS = ["position", "displacement", "active"]
PRIOR_CHANNEL = "prior"

# Per-channel normalization baked into the graph: (value - shift) / scale.
SHIFT = {"position": [0.0, 0.0, 0.0], "displacement": [0.0] * 3, "active": [0.0], "prior": [0.0] * 3}
SCALE = {"position": [0.1] * 3, "displacement": [0.05] * 3, "active": [1.0], "prior": [0.05] * 3}
# Interaction points: rest position (m), prescribed displacement (m) and, in the wider form, the surface
# normal (unit) and the nodal volume (m³), scaled to order one.
INTERACTION_SCALE = [0.1] * 3 + [0.05] * 3 + [1.0] * 3 + [1e-8]
REDUCED_MODES = 12
# Loop steps of the `slow` faulty model per request: seconds on any machine.
SLOW_ITERATIONS = 3_000_000
# Residuals of a few millimetres: the last layer is scaled so outputs are mm-sized.
OUTPUT_SCALE = 0.004
# reduced-forces: the force on each point, N per metre of its prescribed displacement, per axis.
FORCE_GAINS = [100.0, 200.0, 300.0]
# reduced-geometry: the force on each point, N per m³ of its nodal volume, along its normal.
GEOMETRY_GAIN = 1e6


@dataclass(frozen=True)
class Mesh:
    directory: str
    path: Path
    name: str
    content_hash: str
    node_count: int


def describe_mesh(directory: str, path: Path, nak: Path) -> Mesh:
    """Name, hash and node count as nak computes them (`nak mesh info`)."""
    out = subprocess.run([str(nak), "mesh", "info", str(path)], check=True, capture_output=True, text=True).stdout
    fields = {parts[0]: parts[1] for parts in (line.split() for line in out.splitlines()) if len(parts) >= 2}
    return Mesh(directory, path, fields["name"], fields["hash"], int(fields["nodes"]))


class GraphBuilder:
    """Accumulates nodes and initializers with unique names."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.nodes: list[onnx.NodeProto] = []
        self.initializers: list[onnx.TensorProto] = []
        self.count = 0

    def name(self, stem: str) -> str:
        self.count += 1
        return f"{stem}_{self.count}"

    def constant(self, value: np.ndarray, stem: str = "const") -> str:
        name = self.name(stem)
        self.initializers.append(numpy_helper.from_array(value, name))
        return name

    def op(self, op_type: str, inputs: list[str], stem: str | None = None, **attrs: Any) -> str:
        out = self.name(stem or op_type.lower())
        self.nodes.append(helper.make_node(op_type, inputs, [out], **attrs))
        return out

    def linear(self, x: str, fan_in: int, fan_out: int, scale: float = 1.0) -> str:
        limit = np.sqrt(6.0 / (fan_in + fan_out))
        w = (self.rng.uniform(-limit, limit, (fan_in, fan_out)) * scale).astype(np.float32)
        b = (self.rng.uniform(-0.1, 0.1, fan_out) * scale).astype(np.float32)
        return self.op("Add", [self.op("MatMul", [x, self.constant(w, "weight")]), self.constant(b, "bias")])

    def normalized(self, channels: list[str]) -> str:
        shift = np.array(sum((SHIFT[c] for c in channels), []), dtype=np.float32)
        scale = np.array(sum((SCALE[c] for c in channels), []), dtype=np.float32)
        return self.op("Div", [self.op("Sub", ["features", self.constant(shift)]), self.constant(scale)])


def mlp(g: GraphBuilder, channels: list[str], outputs: int = 3) -> str:
    c = len(feature_columns(channels))
    h = g.op("Relu", [g.linear(g.normalized(channels), c, WIDTH)])
    h = g.op("Relu", [g.linear(h, WIDTH, WIDTH)])
    return g.linear(h, WIDTH, outputs, scale=OUTPUT_SCALE)


def pointnet(g: GraphBuilder, channels: list[str]) -> str:
    c = len(feature_columns(channels))
    h = g.op("Relu", [g.linear(g.normalized(channels), c, WIDTH)])
    h = g.op("Relu", [g.linear(h, WIDTH, WIDTH)])
    pooled = g.op("ReduceMax", [h], axes=[1], keepdims=1)  # [B, 1, WIDTH]: the global shape code
    local = g.linear(h, WIDTH, WIDTH)
    glob = g.linear(pooled, WIDTH, WIDTH)
    h = g.op("Relu", [g.op("Add", [local, glob])])  # broadcast the global code over nodes
    return g.linear(h, WIDTH, 3, scale=OUTPUT_SCALE)


def set_encoder(g: GraphBuilder, modes: int, width: int = 6) -> str:
    """`interaction` [B, K, width] → coefficients [B, modes]: per-point MLP, max over the K points, head."""
    x = g.op("Div", ["interaction", g.constant(np.array(INTERACTION_SCALE[:width], np.float32))])
    h = g.op("Relu", [g.linear(x, width, WIDTH)])
    h = g.op("Relu", [g.linear(h, WIDTH, WIDTH)])
    pooled = g.op("ReduceMax", [h], axes=[1], keepdims=0)  # [B, WIDTH], whatever K is
    return g.linear(g.op("Relu", [g.linear(pooled, WIDTH, WIDTH)]), WIDTH, modes)


def random_basis(mesh: Mesh, modes: int, seed: int) -> np.ndarray:
    """Φ [N, 3, M]: smooth enough to be a plausible field, scaled so Φ g is millimetres."""
    rng = np.random.default_rng(seed)
    return (rng.standard_normal((mesh.node_count, 3, modes)) * OUTPUT_SCALE).astype(np.float32)


def write_reduced(
    directory: Path,
    mesh: Mesh,
    seed: int,
    description: str,
    *,
    folded: bool = False,
    basis: np.ndarray | None = None,
    basis_dtype: type = np.float32,
    basis_hash: str | None = None,
    modes: int = REDUCED_MODES,
    width: int = 6,
    declared_width: int | str | None = None,
    forces: str | None = None,
) -> None:
    """A model of the interaction form (docs/design.md §7); `basis` (default: a random one) goes in the graph
    (`folded`) or beside it; `forces` adds a `forces` output: "points" [B, K, 3] as the contract says,
    "two-axes" [B, K, 2] or "per-set" [B, 3] (wrong shape, wrong rank). The input declares `width` values
    a point unless `declared_width` (a number, or a name for a symbolic width) says otherwise."""
    g = GraphBuilder(seed)
    coefficients = set_encoder(g, modes, width)
    outputs = []
    if forces is not None:
        outputs.append(force_output(g, forces))
    phi = random_basis(mesh, modes, seed) if basis is None else basis
    if folded:
        flat = g.constant(phi.reshape(-1, modes).T.copy(), "basis")  # [M, 3N]
        field = g.op("MatMul", [coefficients, flat])
        shape = g.constant(np.array([-1, mesh.node_count, 3], np.int64))
        g.nodes.append(helper.make_node("Reshape", [field, shape], ["displacement"]))
        output = helper.make_tensor_value_info("displacement", TensorProto.FLOAT, ["batch", mesh.node_count, 3])
    else:
        g.nodes.append(helper.make_node("Identity", [coefficients], ["coefficients"]))
        output = helper.make_tensor_value_info("coefficients", TensorProto.FLOAT, ["batch", modes])
    graph = helper.make_graph(
        g.nodes,
        directory.name,
        [
            helper.make_tensor_value_info(
                "interaction",
                TensorProto.FLOAT,
                ["batch", "points", width if declared_width is None else declared_width],
            )
        ],
        [output, *outputs],
        g.initializers,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="nak-test-models")
    model.ir_version = 8
    onnx.checker.check_model(model)
    directory.mkdir(parents=True, exist_ok=True)
    onnx.save(model, directory / "model.onnx")
    if not folded:
        save_file(
            {"basis": phi.astype(basis_dtype)},
            str(directory / "basis.safetensors"),
            metadata={"mesh_hash": basis_hash or mesh.content_hash},
        )
    write_manifest(directory, ["interaction"], "residual", mesh, seed, description, forces=forces is not None)


def force_output(g: GraphBuilder, form: str) -> Any:
    """`forces` = FORCE_GAINS ⊙ u_k per point (or the wrong shapes `two-axes`, `per-set`; or, for `geometry`,
    GEOMETRY_GAIN · V_k n_k from the wider input); its value info."""
    if form == "geometry":
        starts, ends, axis = (g.constant(np.array(v, np.int64)) for v in ([6], [9], [2]))
        normal = g.op("Slice", ["interaction", starts, ends, axis])
        starts, ends = (g.constant(np.array(v, np.int64)) for v in ([9], [10]))
        volume = g.op("Slice", ["interaction", starts, ends, axis])
        scaled = g.op("Mul", [normal, g.op("Mul", [volume, g.constant(np.array([GEOMETRY_GAIN], np.float32))])])
        g.nodes.append(helper.make_node("Identity", [scaled], ["forces"]))
        return helper.make_tensor_value_info("forces", TensorProto.FLOAT, ["batch", "points", 3])
    axes = 2 if form == "two-axes" else 3
    starts, ends, axis = (g.constant(np.array(v, np.int64)) for v in ([3], [3 + axes], [2]))
    u = g.op("Slice", ["interaction", starts, ends, axis])
    scaled = g.op("Mul", [u, g.constant(np.array(FORCE_GAINS[:axes], np.float32))])
    if form == "per-set":
        g.nodes.append(
            helper.make_node("ReduceSum", [scaled, g.constant(np.array([1], np.int64))], ["forces"], keepdims=0)
        )
        return helper.make_tensor_value_info("forces", TensorProto.FLOAT, ["batch", 3])
    g.nodes.append(helper.make_node("Identity", [scaled], ["forces"]))
    return helper.make_tensor_value_info("forces", TensorProto.FLOAT, ["batch", "points", axes])


def feature_columns(channels: list[str]) -> list[str]:
    return [f"{c}{i}" for c in channels for i in range(len(SCALE[c]))]


def fails_when_grasped(g: GraphBuilder, out: str) -> str:
    """Adds zero to `out`, via a Gather whose index is out of range once any node is active: the graph
    runs at warm-up (nothing grasped) and fails on every real request."""
    active = g.op(
        "Slice",
        [
            "features",
            g.constant(np.array([6], np.int64)),
            g.constant(np.array([7], np.int64)),
            g.constant(np.array([2], np.int64)),
        ],
    )
    any_active = g.op("ReduceMax", [active], keepdims=0)
    index = g.op("Cast", [g.op("Mul", [any_active, g.constant(np.array(1e6, np.float32))])], to=TensorProto.INT64)
    picked = g.op("Gather", [g.constant(np.zeros(3, np.float32)), index])
    return g.op("Add", [out, picked])


def slow_when_grasped(g: GraphBuilder, out: str) -> str:
    """Adds zero to `out` after a Loop of SLOW_ITERATIONS tiny steps once any node is active: warm-up
    (nothing grasped) is instant, every real request takes seconds (a model that runs long)."""
    active = g.op(
        "Slice",
        [
            "features",
            g.constant(np.array([6], np.int64)),
            g.constant(np.array([7], np.int64)),
            g.constant(np.array([2], np.int64)),
        ],
    )
    any_active = g.op("ReduceMax", [active], keepdims=0)
    trips = g.op(
        "Cast", [g.op("Mul", [any_active, g.constant(np.array(SLOW_ITERATIONS, np.float32))])], to=TensorProto.INT64
    )
    body = helper.make_graph(
        [
            helper.make_node("Identity", ["cond_in"], ["cond_out"]),
            helper.make_node("Add", ["count_in", "one"], ["count_out"]),
        ],
        "spin",
        [
            helper.make_tensor_value_info("iteration", TensorProto.INT64, []),
            helper.make_tensor_value_info("cond_in", TensorProto.BOOL, []),
            helper.make_tensor_value_info("count_in", TensorProto.FLOAT, []),
        ],
        [
            helper.make_tensor_value_info("cond_out", TensorProto.BOOL, []),
            helper.make_tensor_value_info("count_out", TensorProto.FLOAT, []),
        ],
        [numpy_helper.from_array(np.array(1.0, np.float32), "one")],
    )
    count = g.name("count")
    g.nodes.append(
        helper.make_node(
            "Loop",
            [trips, g.constant(np.array(True)), g.constant(np.array(0.0, np.float32))],
            [count],
            body=body,
        )
    )
    return g.op("Add", [out, g.op("Mul", [count, g.constant(np.array(0.0, np.float32))])])


def write_model(
    directory: Path,
    body: str,
    channels: list[str],
    mode: str,
    mesh: Mesh,
    seed: int,
    description: str,
    input_name: str = "features",
    output_dims: tuple[str | int, str | int, int] = ("batch", "nodes", 3),
    faulty: bool = False,
    slow: bool = False,
) -> None:
    g = GraphBuilder(seed)
    out = mlp(g, channels, int(output_dims[2])) if body == "mlp" else pointnet(g, channels)
    if faulty:
        out = fails_when_grasped(g, out)
    if slow:
        out = slow_when_grasped(g, out)
    g.nodes.append(helper.make_node("Identity", [out], ["displacement"]))
    c = len(feature_columns(channels))
    graph = helper.make_graph(
        g.nodes,
        directory.name,
        [helper.make_tensor_value_info("features", TensorProto.FLOAT, ["batch", "nodes", c])],
        [helper.make_tensor_value_info("displacement", TensorProto.FLOAT, list(output_dims))],
        g.initializers,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="nak-test-models")
    model.ir_version = 8
    onnx.checker.check_model(model)
    if input_name != "features":
        model.graph.input[0].name = input_name
        for node in model.graph.node:
            node.input[:] = [input_name if i == "features" else i for i in node.input]
    directory.mkdir(parents=True, exist_ok=True)
    onnx.save(model, directory / "model.onnx")
    write_manifest(directory, channels, mode, mesh, seed, description)


def write_manifest(
    directory: Path, channels: list[str], mode: str, mesh: Mesh, seed: int, description: str, forces: bool = False
) -> None:
    listed = ", ".join(f'"{c}"' for c in channels)
    forces_section = '\n[forces]\nmode = "direct"\n' if forces else ""
    (directory / "manifest.toml").write_text(
        f"""# Test model made by tests/models/make_models.py: fixed random weights, not trained.
[model]
name = "{directory.name}"
mode = "{mode}"
method = "{"res" if mode == "residual" else "base"}"
regime = "linear"
inputs = [{listed}]
description = "{description}"

[mesh]
name = "{mesh.name}"
content_hash = "{mesh.content_hash}"
node_count = {mesh.node_count}

[prior]
poisson_ratio = 0.45
epsilon_m = 0.05
lambda = 0.001

[provenance]
made_by = "tests/models/make_models.py"
seed = {seed}
{forces_section}"""
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--nak", type=Path, default=ROOT / "target" / "debug" / "nak")
    args = parser.parse_args()
    meshes = [
        describe_mesh("phantom-liver", ROOT / "models" / "phantom-liver" / "liver.msh", args.nak),
        describe_mesh("phantom-liver-coarse", ROOT / "models" / "phantom-liver" / "liver-coarse.msh", args.nak),
    ]
    models = [
        ("mlp-residual", "mlp", BASE_CHANNELS, "residual", "per-node MLP 7-64-64-3"),
        (
            "mlp-direct-prior",
            "mlp",
            BASE_CHANNELS + [PRIOR_CHANNEL],
            "direct",
            "per-node MLP 10-64-64-3 reading the prior",
        ),
        ("pointnet-residual", "pointnet", BASE_CHANNELS, "residual", "PointNet-style, global max-pool, width 64"),
        ("pointnet-direct", "pointnet", BASE_CHANNELS, "direct", "PointNet-style, global max-pool, width 64"),
    ]
    for mesh in meshes:
        for seed, (name, body, channels, mode, description) in enumerate(models, start=1):
            write_model(HERE / mesh.directory / name, body, channels, mode, mesh, seed, description)
    coarse = meshes[1]
    faulty = HERE / "faulty"
    write_model(
        faulty / "fails-at-run-time" / "fails-at-run-time",
        "mlp",
        BASE_CHANNELS,
        "residual",
        coarse,
        11,
        "fails on any request with a grasp",
        faulty=True,
    )
    write_model(
        faulty / "slow" / "slow",
        "mlp",
        BASE_CHANNELS,
        "residual",
        coarse,
        14,
        "spins for seconds on any request with a grasp",
        slow=True,
    )
    write_model(
        faulty / "wrong-input-name" / "wrong-input-name",
        "mlp",
        BASE_CHANNELS,
        "residual",
        coarse,
        12,
        "input named x",
        input_name="x",
    )
    write_model(
        faulty / "wrong-output-shape" / "wrong-output-shape",
        "mlp",
        BASE_CHANNELS,
        "residual",
        coarse,
        13,
        "declares 4 output channels",
        output_dims=("batch", "nodes", 4),
    )
    reduced: list[tuple[str, dict[str, Any]]] = [
        ("reduced-residual", {}),
        ("reduced-residual-f16", {"basis_dtype": np.float16}),
        ("reduced-folded", {"folded": True}),
        ("reduced-forces", {"forces": "points"}),
        ("reduced-geometry", {"forces": "geometry", "width": 10}),
    ]
    for name, extra in reduced:
        # One encoder and one basis (seed 21) in three forms.
        write_reduced(HERE / coarse.directory / name, coarse, 21, f"set encoder over K points, {name}", **extra)
    bad_reduced: list[tuple[str, dict[str, Any]]] = [
        ("interaction-wrong-width", {"width": 5}),
        ("basis-wrong-size", {"basis": random_basis(coarse, REDUCED_MODES, 1)[:-1]}),
        ("basis-other-mesh", {"basis_hash": meshes[0].content_hash}),
        ("basis-modes-mismatch", {"basis": random_basis(coarse, REDUCED_MODES - 4, 1)}),
        ("forces-two-axes", {"forces": "two-axes"}),
        ("forces-per-set", {"forces": "per-set"}),
        ("interaction-symbolic-width", {"declared_width": "values"}),
    ]
    for seed, (name, extra) in enumerate(bad_reduced, start=31):
        write_reduced(faulty / name / name, coarse, seed, name, **extra)
    print(f"wrote models for {', '.join(m.directory for m in meshes)} and faulty cases under {HERE}")


if __name__ == "__main__":
    main()
