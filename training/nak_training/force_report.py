"""Grasp forces against the finite elements, as nak serves them: per model, `nak eval`'s force error on
the test split per subset; a figure of each served force component against the FEM's; what a force
head costs a request (the graph against the same network exported without it, both run as nak runs
them); and how
the FEM's force grows with the nodes a grasper holds, which a head must see to learn it.

python -m nak_training forces --data DATA --runs RUNS --model pod-base-forces-nl   (writes docs/reports/forces*)
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import onnxruntime  # noqa: E402
import torch  # noqa: E402
from safetensors.numpy import load_file  # noqa: E402

from .config import load_config  # noqa: E402
from .dataset import Dataset, Mesh, Sample, is_failed, open_dataset, read_json  # noqa: E402
from .errors import TrainingInputError  # noqa: E402
from .evaluate import read_manifest, refuse_scoring_on_its_training_set  # noqa: E402
from .export import trace_interaction_graph  # noqa: E402
from .grasp_served import served_form  # noqa: E402
from .reduced import GEOMETRY_WIDTH, INTERACTION_WIDTH, InteractionGraph  # noqa: E402
from .reduced_train import interaction_input, load_reduced  # noqa: E402
from .served import Nak  # noqa: E402
from .static_sizes import RELATIVE_TOLERANCE  # noqa: E402

# The linearization the nonlinear networks' forces build on, scored beside them.
PRIOR = "green-tangent"
SUBSETS = ("single", "multi", "combined")
# Each timed request runs through both graphs, in turn, this many times (even: each graph's session is
# opened first in half of them); a head's cost is the median of the differences request by request,
# which the machine's drift between runs cannot reach.
TIMING_ROUNDS = 6
TIMED_REQUESTS = 400
# Single-grasper pushes deeper than this (metres) are grouped by held-node count: shallow pushes would
# mix the count's effect with the depth's.
DEEP_PUSH = 0.05
# Grasps grouped by the cosine of their displacement with the outward normal of the nodes they hold:
# a push into the organ compresses the tissue under it, a pull stretches it.
DIRECTIONS = ((-1.0, -0.5, "into the organ"), (-0.5, 0.0, "oblique, in"), (0.0, 0.5, "oblique, out"), (0.5, 1.0, "out"))


def write_force_report(
    data: Path, models: list[Path], nak: Path, mesh: Path, out: Path, runs: Path, prior: str = PRIOR
) -> Path:
    """Scores `prior` (green-tangent or green-linear) and the model directories `models` (each with a
    [forces] section, its run under `runs`) on the test split of `data`; writes `out`.md and the figure
    `out`/served-against-fem.png."""
    dataset = open_dataset(data)
    test = dataset.load("test").samples
    truth = {s.index: s.forces for s in test if s.forces is not None}
    if not truth:
        raise TrainingInputError(data, "its test split stores no grasp forces (regenerate it with nak datagen)")
    for directory in models:
        manifest = read_manifest(directory)
        if "forces" not in manifest:
            raise TrainingInputError(directory, "has no [forces] section: not a model with learned forces")
        refuse_scoring_on_its_training_set(directory, manifest, data)
    names = [prior, *(d.name for d in models)]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "models"
        root.mkdir()
        for directory in models:
            (root / directory.name).symlink_to(directory.resolve(), target_is_directory=True)
        served = Nak(nak, mesh)
        flags = ["--models", str(root), f"--{prior}"]
        reports = {name: evaluation(served, data, name, flags, Path(tmp)) for name in names}
        forces = {name: served_forces(served, data, name, flags, Path(tmp)) for name in names}
        costs = {d.name: head_cost(d, runs, dataset.mesh, test[:TIMED_REQUESTS], Path(tmp)) for d in models}
    out.mkdir(parents=True, exist_ok=True)
    figure = out / "served-against-fem.png"
    plot(truth, forces, {s.index: s.subset for s in test}, figure)
    path = out.with_suffix(".md")
    misses = by_direction(test, dataset.mesh.normals.numpy(), truth, {d.name: forces[d.name] for d in models})
    path.write_text(
        markdown(dataset.root, reports, costs, figure.relative_to(path.parent)) + misses + force_by_count(dataset)
    )
    return path


def push_cosines(sample: Sample, normals: np.ndarray, grasps: int) -> np.ndarray:
    """Per grasp of `sample` (`grasps` of them), the cosine of its displacement with the mean outward normal
    of the nodes it holds [G] (NaN for a grasp that shows no node of its own: each node counts for the
    first grasp holding it)."""
    cosines = np.full(grasps, np.nan)
    for g in range(grasps):
        held = sample.grasp_of_point == g
        if held.any():
            u = sample.displacements[held][0]
            n = normals[sample.nodes[held]].sum(0)
            cosines[g] = u @ n / max(float(np.linalg.norm(u) * np.linalg.norm(n)), 1e-30)
    return cosines


def by_direction(
    samples: list[Sample], normals: np.ndarray, truth: dict[int, np.ndarray], served: dict[str, dict[int, np.ndarray]]
) -> str:
    """A table of each model's mean relative grasp-force error per subset and push direction (DIRECTIONS)."""
    if not served:
        return ""
    cosines = {s.index: push_cosines(s, normals, len(truth[s.index])) for s in samples if s.index in truth}
    subset = {s.index: s.subset for s in samples}
    inner_edges = [hi for _, hi, _ in DIRECTIONS[:-1]]
    header = " | ".join(f"{name} ({lo:g} to {hi:g})" for lo, hi, name in DIRECTIONS)
    lines = [
        "",
        "Where the heads miss: the mean |F̂ − F| / |F| (and the grasps) by the direction of the grasp's",
        "displacement, the cosine of its angle with the outward surface normal of the nodes it holds:",
        "",
        f"| Model | Subset | {header} |",
        "|---|---|" + "---:|" * len(DIRECTIONS),
    ]
    for name, forces in served.items():
        for kind in ("single", "multi"):
            errors: list[list[float]] = [[] for _ in DIRECTIONS]
            for index, fem in truth.items():
                if subset.get(index) != kind or index not in forces:
                    continue
                relative = np.linalg.norm(forces[index][: len(fem)] - fem, axis=1) / np.linalg.norm(fem, axis=1)
                for error, cosine in zip(relative, cosines[index], strict=True):
                    if not np.isnan(cosine):
                        errors[int(np.digitize(cosine, inner_edges))].append(float(error))
            cells = " | ".join(f"{100 * np.mean(e):.1f} % ({len(e)})" if e else "–" for e in errors)
            lines.append(f"| `{name}` | {kind} | {cells} |")
    return "\n".join(lines) + "\n"


def force_by_count(dataset: Dataset) -> str:
    """A table of the median FEM force of single-grasper pushes deeper than DEEP_PUSH, by the number of
    nodes the grasper holds, over every converged sample of the set."""
    by_count: dict[int, list[float]] = {}
    for chunk in dataset.complete_chunks():
        for record in read_json(dataset.root / f"chunk-{chunk:05d}.json"):
            grasps = record.get("grasps", [])
            if record.get("subset") != "single" or is_failed(record) or len(grasps) != 1 or "force" not in grasps[0]:
                continue
            if np.linalg.norm(grasps[0]["displacement"]) > DEEP_PUSH:
                by_count.setdefault(len(grasps[0]["nodes"]), []).append(float(np.linalg.norm(grasps[0]["force"])))
    if not by_count:
        return ""
    lines = [
        "",
        f"How the FEM's force grows with what a grasper holds: single-grasper pushes deeper than {DEEP_PUSH * 100:g} cm,",
        "every converged sample of the set, by the number of nodes held:",
        "",
        "| Nodes held | Grasps | median \\|F\\| |",
        "|---:|---:|---:|",
    ]
    lines += [f"| {n} | {len(f)} | {float(np.median(f)):.2f} N |" for n, f in sorted(by_count.items())]
    return "\n".join(lines) + "\n"


def field_only(model: Path, runs: Path, mesh: Mesh, example: np.ndarray, into: Path) -> None:
    """The network of the model directory `model` exported as it is, less its force head, written to `into`:
    from its run under `runs` (runs are not committed: train it again), checked to give `model`'s field.
    The served form computes a head's first layer with its encoder's (grasp_served.py), so the same graph
    with its `forces` output cut away would still compute part of the head."""
    config = load_config(model / "config.toml")
    net, basis = load_reduced(runs / config.name, config)
    net.forces = None  # the network as it would be exported without a head: its field alone
    folded = config.form == "graph"
    graph = InteractionGraph(net, basis if folded else None, mesh.positions, folded, served_form(net))
    trace_interaction_graph(graph, torch.from_numpy(example), into)
    ours, theirs = (served_session(g).run(None, {"interaction": example})[0] for g in (model / "model.onnx", into))
    difference = float(np.abs(ours - theirs).max() / max(float(np.abs(theirs).max()), 1e-30))
    if difference > RELATIVE_TOLERANCE:
        raise TrainingInputError(
            runs / config.name,
            f"its field differs from {model}'s by {difference:.1e} (relative): not the run it came from",
        )


def evaluation(served: Nak, data: Path, model: str, flags: list[str], tmp: Path) -> dict[str, Any]:
    """`nak eval`'s report of `model` on the test split."""
    output = tmp / f"{model}-eval.json"
    served.run(
        "eval", "--data", str(data), "--model", model, "--split", "test", "--output", str(output),
        "--latency-samples", "0", *flags,
    )  # fmt: skip
    report: dict[str, Any] = json.loads(output.read_text())
    return report


def served_forces(served: Nak, data: Path, model: str, flags: list[str], tmp: Path) -> dict[int, np.ndarray]:
    """Each test sample's served grasp forces [G, 3], by dataset index."""
    output = tmp / f"{model}-fields.safetensors"
    served.run(
        "dataset", "fields", "--data", str(data), "--model", model, "--split", "test", "--out", str(output), *flags
    )
    tensors = load_file(str(output))
    if "grasp_forces" not in tensors:
        raise TrainingInputError(model, "gives no grasp forces")
    return {int(i): f for i, f in zip(tensors["index"], tensors["grasp_forces"], strict=True)}


def served_session(graph: Path) -> onnxruntime.InferenceSession:
    """An ONNX Runtime session set as nak sets one for an interaction graph (src/model/onnx.rs): one
    intra-op thread that does not spin, every graph optimization."""
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
    return onnxruntime.InferenceSession(str(graph), options, providers=["CPUExecutionProvider"])


def timing_requests(mesh: Mesh, samples: list[Sample], width: int) -> list[np.ndarray]:
    """What nak feeds an interaction graph of input `width` for each sample's grasps, [1, K, width] f32."""
    requests = []
    for sample in samples:
        ids = torch.from_numpy(sample.nodes)
        displacements = torch.from_numpy(sample.displacements)
        geometry, depth = width > INTERACTION_WIDTH, width > INTERACTION_WIDTH + GEOMETRY_WIDTH
        request = interaction_input(mesh, ids, mesh.positions[ids], displacements, geometry, depth)
        requests.append(request[None].numpy())
    return requests


def head_cost(model: Path, runs: Path, mesh: Mesh, samples: list[Sample], tmp: Path) -> dict[str, float]:
    """The graph's time a request (µs, median) with its force head and without (`field_only`), and the
    head's: the median of the two's difference request by request (`paired_times`)."""
    graph = model / "model.onnx"
    width = int(served_session(graph).get_inputs()[0].shape[-1])
    requests = timing_requests(mesh, samples, width)
    without = tmp / f"{model.name}-field-only.onnx"
    field_only(model, runs, mesh, requests[0], without)
    times = paired_times((graph, without), requests)
    return {
        "with": float(np.median(times[0])),
        "without": float(np.median(times[1])),
        "head": float(np.median(times[0] - times[1])),
        "requests": len(requests),
    }


def paired_times(graphs: tuple[Path, Path], requests: list[np.ndarray]) -> np.ndarray:
    """[2, TIMING_ROUNDS, requests] µs: each request through both graphs in turn, the order alternating,
    in TIMING_ROUNDS rounds; each round opens both sessions anew, the one opened first alternating too
    (which session was opened first moved the difference between two copies of one graph by 4–8 µs,
    as much as half a head), and runs every request through both once before it is timed. The time
    is the calling thread's CPU time (ONNX Runtime runs a one-thread session on it), which other work
    on the machine does not stretch as it stretches the wall clock."""
    times = np.zeros((2, TIMING_ROUNDS, len(requests)))
    for r in range(TIMING_ROUNDS):
        order = (0, 1) if r % 2 == 0 else (1, 0)
        opened = {which: served_session(graphs[which]) for which in order}
        sessions = (opened[0], opened[1])
        for request in requests:
            for session in sessions:
                session.run(None, {"interaction": request})
        for i, request in enumerate(requests):
            for which in order if i % 2 == 0 else order[::-1]:
                start = time.thread_time_ns()
                sessions[which].run(None, {"interaction": request})
                times[which, r, i] = (time.thread_time_ns() - start) / 1e3
        del sessions, opened  # closed before the next round opens its own, in the same memory
    return times


def plot(
    truth: dict[int, np.ndarray], forces: dict[str, dict[int, np.ndarray]], subset: dict[int, str], path: Path
) -> None:
    """One panel per model: every grasp's served force components against the FEM's, by subset."""
    fig, axes = plt.subplots(1, len(forces), figsize=(4.2 * len(forces), 4.2), squeeze=False)
    largest = max(float(np.abs(f).max()) for f in truth.values())
    for ax, (name, served) in zip(axes[0], forces.items(), strict=True):
        limit = 1.1 * max(largest, max(float(np.abs(f).max()) for f in served.values()))
        for kind, color in (("single", "tab:blue"), ("multi", "tab:orange")):
            pairs = [(truth[i], served[i][: len(truth[i])]) for i in truth if subset.get(i) == kind and i in served]
            if pairs:
                fem = np.concatenate([t.reshape(-1) for t, _ in pairs])
                got = np.concatenate([s.reshape(-1) for _, s in pairs])
                ax.scatter(fem, got, s=6, alpha=0.6, color=color, label={"single": "one grasper", "multi": "two"}[kind])
        ax.plot([-limit, limit], [-limit, limit], color="0.4", linewidth=0.8)
        ax.set(xlim=(-limit, limit), ylim=(-limit, limit), title=name, xlabel="FEM force component (N)")
        ax.set_aspect("equal")
    axes[0][0].set_ylabel("served force component (N)")
    axes[0][0].legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(data: Path, reports: dict[str, dict[str, Any]], costs: dict[str, dict[str, float]], figure: Path) -> str:
    lines = [
        "# Grasp forces against the finite elements",
        "",
        f"Written by `python -m nak_training forces` on the test split of `{data}`; each model through the",
        "serving engine (`nak eval`, `nak dataset fields`). Per grasp: |F̂ − F| / |F| (mean and median),",
        "|F̂| / |F| (median) and the angle between F̂ and F (median).",
        "",
        "| Model | Subset | Grasps | mean \\|F̂ − F\\| / \\|F\\| | median | median \\|F̂\\| / \\|F\\| | median angle |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for name, report in reports.items():
        for subset in SUBSETS:
            s = report["grasp_forces"].get(subset)
            if s:
                lines.append(
                    f"| `{name}` | {subset} | {s['grasps']} | {100 * s['mean_relative_error']:.1f} % | "
                    f"{100 * s['median_relative_error']:.1f} % | {s['median_magnitude_ratio']:.3f} | "
                    f"{s['median_angle_deg']:.1f}° |"
                )
    lines += ["", f"![Served against FEM force components]({figure})", ""]
    if costs:
        lines += [
            "What the force head costs a request: the graph against the same network exported without its head",
            "(from its run; the served form computes the head's first layer with its encoder's, so cutting the",
            "`forces` output away would leave part of it), both run by ONNX Runtime as nak runs an interaction",
            f"graph (one intra-op thread, no spinning, every graph optimization) on the first {TIMED_REQUESTS} test requests",
            f"or fewer, each through both graphs in turn, the order alternating, in {TIMING_ROUNDS} rounds, each opening both",
            "sessions anew, first the one and then the other in turn (the session opened first ran slower); the",
            "calling thread's CPU time, median over requests and rounds; the head's cost is the median of the",
            "differences request by request:",
            "",
            "| Model | requests | with its head | without | the head |",
            "|---|---:|---:|---:|---:|",
        ]
        for name, c in costs.items():
            lines.append(
                f"| `{name}` | {c['requests']:.0f} | {c['with']:.1f} µs | {c['without']:.1f} µs | **{c['head']:.1f} µs** |"
            )
        lines.append("")
    return "\n".join(lines)
