"""The results page (docs/reports/models.md): every trained model's test-split DCM through nak in the layout of
the paper's Table 2, beside the paper's figures and the Kelvinlet and green-linear baselines, and nak's
version of the paper's Fig. 2 (DCM against the engine's time per request) as a PNG.

Everything is read from the model manifests' [metrics] (written by `evaluate`) or measured now with
`nak eval` (the baselines), so the page can be regenerated with one command.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import tomllib
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Callable
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from .config import parse_config  # noqa: E402
from .dataset import open_dataset  # noqa: E402
from .evaluate import metrics_of, nak_eval  # noqa: E402
from .export import CEILING_PREFIX  # noqa: E402

ARCHITECTURES = {
    "pointnet": "PointNet",
    "deepset": "DeepSet U-Net",
    "isab": "ISAB (SAB)",
    "pod": "POD basis + set encoder",
    "deeponet": "DeepONet + set encoder",
    "gnn": "Mesh GNN (PhysGNN-style)",
}
SIZED = ("pointnet", "deepset", "isab", "gnn")
METHODS = ("base", "res", "reg")
METHOD_LABEL = {"base": "Base", "res": "+Res", "reg": "+Reg"}
# Table 2 columns: (what the model was trained on, the test subset scored, heading).
COLUMNS = (("single", "single", "Indiv."), ("multi", "multi", "Comb."), ("all", "combined", "Multi"))
# The paper's Tables 2 (linear) and 3 (nonlinear), code form of DCM, for the rows nak has counterparts
# of (its U-Net is nak's DeepSet U-Net, its SAB nak's ISAB, its PhysGNN nak's mesh GNN).
PAPER = {
    "linear": {
        "pointnet": {"single": (94.23, 94.66, 96.54), "multi": (89.79, 90.11, 91.22), "all": (94.00, 94.12, 95.01)},
        "deepset": {"single": (92.11, 93.56, 94.04), "multi": (88.23, 89.67, 90.01), "all": (91.20, 92.33, 92.88)},
        "isab": {"single": (93.42, 94.60, 96.03), "multi": (88.05, 89.91, 91.02), "all": (92.54, 93.66, 94.42)},
        "gnn": {"single": (90.12, 91.77, 92.65), "multi": (86.38, 88.10, 88.66), "all": (89.55, 90.96, 91.54)},
    },
    "nonlinear": {
        "pointnet": {"single": (81.25, 84.65, 85.05), "multi": (79.56, 82.66, 83.33), "all": (83.25, 84.75, 85.21)},
        "deepset": {"single": (80.56, 84.22, 84.88), "multi": (76.91, 79.83, 82.10), "all": (78.10, 80.45, 81.33)},
        "isab": {"single": (80.75, 84.44, 84.75), "multi": (78.88, 81.50, 82.83), "all": (81.22, 83.01, 84.00)},
        "gnn": {"single": (78.05, 82.19, 82.79), "multi": (75.30, 79.18, 80.83), "all": (77.73, 80.58, 81.34)},
    },
}
PAPER_KELVINLET = {
    "linear": {"single": 65.24, "multi": 64.33, "all": 64.82},
    "nonlinear": {"single": 58.88, "multi": 51.67, "all": 55.56},
}
# Nonlinear models are named like the linear ones with this suffix (training/configs/nonlinear).
NONLINEAR_SUFFIX = "-nl"


@dataclass(frozen=True)
class Entry:
    name: str
    architecture: str
    method: str
    trained_on: str
    epsilon: float
    metrics: dict[str, Any]
    regime: str = "linear"
    prior: str = "kelvinlet"
    train_samples: int = 0
    # The training configuration but for its name and sample count: models trained alike on different
    # amounts of data share it ("" when the model directory has no config.toml).
    recipe: str = ""


def read_models(roots: list[Path]) -> list[Entry]:
    entries = []
    for manifest_path in sorted(p for root in roots for p in root.glob("*/manifest.toml")):
        manifest = tomllib.loads(manifest_path.read_text())
        provenance = manifest.get("provenance", {})
        if "architecture" not in provenance or "dcm_combined" not in manifest.get("metrics", {}):
            continue
        entries.append(
            Entry(
                name=manifest["model"]["name"],
                architecture=provenance["architecture"],
                method=manifest["model"]["method"],
                trained_on=provenance["trained_on"],
                epsilon=manifest["prior"]["epsilon_m"],
                metrics=manifest["metrics"],
                regime=manifest["model"]["regime"],
                prior=manifest["prior"].get("model", "kelvinlet"),
                train_samples=int(provenance.get("train_samples", 0)),
                recipe=recipe(manifest_path.parent / str(provenance.get("config", "config.toml"))),
            )
        )
    return entries


def recipe(config_path: Path) -> str:
    """How a configuration trains, without what it trains on (its name, sample count and held-out split)
    or on how many threads: two models of one recipe are points of one learning curve."""
    if not config_path.is_file():
        return ""
    # Through the parser, so that a key added since (with its default) does not split one recipe in two.
    config = parse_config(tomllib.loads(config_path.read_text()), str(config_path)).to_dict()
    for key in ("name", "train_samples", "holdout", "threads"):
        config.pop(key, None)
    return json.dumps(config, sort_keys=True)


def baseline(
    nak: Path, data: Path, mesh: Path, model: str, epsilon: float | None = None, split: str = "test"
) -> dict[str, Any]:
    """`nak eval` of the Kelvinlet (at the mesh's ε, or another), green-linear or green-tangent on `split`."""
    if epsilon is None:
        return metrics_of(nak_eval(nak, data, model, mesh, None, split))
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / mesh.name
        shutil.copy(mesh, copy)
        config = (mesh.parent / "model.toml").read_text()
        lines = [f"epsilon_m = {epsilon}" if line.startswith("epsilon_m") else line for line in config.splitlines()]
        (Path(tmp) / "model.toml").write_text("\n".join(lines) + "\n")
        return metrics_of(nak_eval(nak, data, model, copy, None, split))


def model_name(architecture: str, method: str, trained_on: str, regime: str = "linear") -> str:
    """The naming of training/configs: `<architecture>-<method>` plus `-indiv` / `-comb` for the
    models trained on one subset, and `-nl` for the nonlinear regime (training/configs/nonlinear)."""
    name = f"{architecture}-{method}" + {"single": "-indiv", "multi": "-comb", "all": ""}[trained_on]
    return name + (NONLINEAR_SUFFIX if regime == "nonlinear" else "")


def cell(
    entries: list[Entry], architecture: str, method: str, trained_on: str, subset: str, key: str, regime: str
) -> str:
    wanted = model_name(architecture, method, trained_on, regime)
    value = next((e.metrics.get(f"{key}_{subset}") for e in entries if e.name == wanted), None)
    return "–" if value is None else f"{value:.2f}"


def table(
    entries: list[Entry], key: str, baselines: dict[str, dict[str, Any]], with_paper: bool, regime: str = "linear"
) -> list[str]:
    head = "| model | " + " | ".join(f"{h} {METHOD_LABEL[m]}" for _, _, h in COLUMNS for m in METHODS) + " |"
    lines = [head, "|---" * (1 + 3 * len(COLUMNS)) + "|"]
    paper_rows = PAPER[regime]
    for arch, label in ARCHITECTURES.items():
        cells = [
            cell(entries, arch, m, trained, subset, key, regime) for trained, subset, _ in COLUMNS for m in METHODS
        ]
        if all(c == "–" for c in cells):
            continue
        lines.append(f"| {label} (nak{', cpu size' if arch in SIZED else ''}) | " + " | ".join(cells) + " |")
        # +Res on an exact linear answer instead of the Kelvinlet (configs `<arch>-res-gl…`, `-res-gt…`).
        for method, prior in (("res-gl", "green-linear"), ("res-gt", "green-tangent")):
            on_green = [
                cell(entries, arch, method, trained, subset, key, regime) if m == "res" else ""
                for trained, subset, _ in COLUMNS
                for m in METHODS
            ]
            if any(c not in ("", "–") for c in on_green):
                lines.append(f"| {label}, +Res on {prior} (nak) | " + " | ".join(on_green) + " |")
        if with_paper and arch in paper_rows:
            paper = [f"{paper_rows[arch][trained][i]:.2f}" for trained, _, _ in COLUMNS for i in range(3)]
            lines.append(f"| {label} (paper, GPU) | " + " | ".join(paper) + " |")
    for name, metrics in baselines.items():
        values = [metrics.get(f"{key}_{subset}") for _, subset, _ in COLUMNS]
        # No training: one figure per column group, under Base.
        cells = [("–" if v is None else f"{v:.2f}") if m == "base" else "" for v in values for m in METHODS]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if with_paper:
        kelvinlet = PAPER_KELVINLET[regime]
        cells = [f"{kelvinlet[trained]:.2f}" if m == "base" else "" for trained, _, _ in COLUMNS for m in METHODS]
        lines.append("| Kelvinlet (paper) | " + " | ".join(cells) + " |")
    return lines


def figure(entries: list[Entry], baselines: dict[str, dict[str, Any]], path: Path) -> None:
    """Both regimes on one plot, as the paper's Fig. 2: linear filled, nonlinear hollow."""
    markers = {"pointnet": "o", "deepset": "s", "isab": "^", "pod": "D", "deeponet": "P", "gnn": "h"}
    colours = {"base": "#9e9e9e", "res": "#1f77b4", "reg": "#d62728"}
    fig, ax = plt.subplots(figsize=(8.5, 5.5))
    names: list[tuple[str, float, float]] = []
    for e in entries:
        if e.trained_on != "all" or curve_point(e.name):
            continue
        x, y = e.metrics.get("total_ms_p50"), e.metrics.get("dcm_code_combined")
        if x is None or y is None:
            continue
        colour = colours[e.method]
        face = colour if e.regime == "linear" else "white"
        ax.scatter(x, y, marker=markers[e.architecture], s=70, color=face, edgecolors=colour, linewidths=1.6)
        names.append((e.name, x, y))
    for name, metrics in baselines.items():
        x, y = metrics.get("total_ms_p50"), metrics.get("dcm_code_combined")
        if x is not None and y is not None:
            face = "white" if "nonlinear" in name else "#2ca02c"
            ax.scatter(x, y, marker="*", s=160, color=face, edgecolors="#2ca02c", linewidths=1.4)
            names.append((name, x, y))
    for arch, marker in markers.items():
        if any(e.architecture == arch for e in entries):
            ax.scatter([], [], marker=marker, color="white", edgecolors="black", label=ARCHITECTURES[arch])
    for method, colour in colours.items():
        ax.scatter([], [], marker="o", color=colour, label=METHOD_LABEL[method])
    ax.scatter([], [], marker="o", color="white", edgecolors="black", label="hollow: nonlinear regime")
    ax.set_xscale("log")
    labels = (
        "engine time per request, p50 (ms, log scale; 2 vCPUs, one request at a time)",
        "DCM, code form (%), test split, all samples",
        "nak on the phantom liver: accuracy against served time (cf. the paper's Fig. 2)",
    )
    save(fig, ax, path, labels, legend_size=7, annotate=lambda: place_labels(ax, names, fontsize=6))


# Where a point's name may go relative to it (points), tried in this order.
LABEL_OFFSETS = [(7, -3), (-7, -3), (7, 5), (-7, 5), (7, -11), (-7, -11), (0, 10), (0, -17), (7, 13), (-7, -19)]


def alignment(offset: tuple[int, int]) -> str:
    """A label left of its point ends there, one right of it starts there, one above or below is centred."""
    return "right" if offset[0] < 0 else "left" if offset[0] > 0 else "center"


def place_labels(ax: Any, names: list[tuple[str, float, float]], fontsize: float = 7) -> None:
    """Names beside their points, each at the first offset where its text, as drawn, stays between the
    axes' sides and overlaps no marker and no name already placed, else where it overlaps least
    (points close together otherwise print their names over each other). Call it once the layout is
    final: it measures in display space."""
    renderer = ax.figure.canvas.get_renderer()
    inside = ax.get_window_extent(renderer)
    half = 5 * ax.figure.dpi / 72  # a marker's half width, display pixels
    markers = []
    for _, x, y in names:
        px, py = ax.transData.transform((x, y))
        markers.append((px - half, py - half, px + half, py + half))
    placed: list[tuple[float, float, float, float]] = []

    def overlap(b: Any, own: int) -> float:
        outside = max(0.0, inside.x0 - b.x0) + max(0.0, b.x1 - inside.x1)
        others = [t for i, t in enumerate(markers) if i != own] + placed
        shared = sum(
            max(0.0, min(b.x1, t[2]) - max(b.x0, t[0])) * max(0.0, min(b.y1, t[3]) - max(b.y0, t[1])) for t in others
        )
        return 1e6 * outside + shared

    for i in sorted(range(len(names)), key=lambda i: (-names[i][2], names[i][1])):
        name, x, y = names[i]
        label = ax.annotate(name, (x, y), textcoords="offset points", xytext=LABEL_OFFSETS[0], fontsize=fontsize)
        costs = []
        for offset in LABEL_OFFSETS:
            label.xyann = offset
            label.set_horizontalalignment(alignment(offset))
            costs.append((overlap(label.get_window_extent(renderer), i), offset))
            if costs[-1][0] == 0:
                break
        offset = min(costs, key=lambda c: c[0])[1]
        label.xyann = offset
        label.set_horizontalalignment(alignment(offset))
        b = label.get_window_extent(renderer)
        placed.append((b.x0, b.y0, b.x1, b.y1))


def save(
    fig: Any,
    ax: Any,
    path: Path,
    labels: tuple[str, str, str],
    legend_size: int,
    annotate: Callable[[], None] | None = None,
) -> None:
    """Axis labels and title, grid, legend, `annotate` once the layout is final, and the PNG."""
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    ax.set_title(labels[2])
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=legend_size, loc="lower right")
    fig.tight_layout()
    if annotate is not None:
        annotate()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def scored_before_held_nodes(e: Entry) -> bool:
    """Whether the model was scored before nak answered held nodes with their prescribed displacement
    (docs/design.md §7): its manifest's scores are of the field as the model alone gave it."""
    return "held_nodes" not in e.metrics


def mark(e: Entry) -> str:
    """The footnote mark of a score from before held nodes were prescribed ("" after)."""
    return "\\*" if scored_before_held_nodes(e) else ""


def marked(e: Entry) -> str:
    return f"`{e.name}`{mark(e)}"


def curve_point(name: str) -> bool:
    """Whether a model is a learning curve's point (`<config>-nN`), trained on part of the data."""
    return name.rpartition("-n")[2].isdigit()


def learning_curve(entries: list[Entry], path: Path) -> list[str]:
    """Test DCM against the number of training samples for configurations trained at several sizes
    (`--train-samples N` names them `<config>-nN`; a model of another name trained alike, on more
    data, joins its curve); figure and table lines, empty without any."""
    curves: dict[str, list[Entry]] = {}
    for e in entries:
        if curve_point(e.name):
            curves.setdefault(e.name.rpartition("-n")[0], [])
    for base in curves:
        own = next((e for e in entries if e.name == base), None)
        curves[base] = sorted(
            (
                e
                for e in entries
                if e.name == base
                or e.name.startswith(f"{base}-n")
                or (own is not None and own.recipe != "" and (e.recipe, e.regime) == (own.recipe, own.regime))
            ),
            key=lambda e: e.train_samples,
        )
    if not curves:
        return []
    fig, ax = plt.subplots(figsize=(6.5, 4))
    lines = ["| configuration | training samples → DCM on its scored samples (volume form) |", "|---|---|"]
    for base, points in curves.items():
        xs, ys = [e.train_samples for e in points], [e.metrics["dcm_combined"] for e in points]
        (line,) = ax.plot(xs, ys, marker="o", label=base)
        before = [(x, y) for x, y, e in zip(xs, ys, points, strict=True) if scored_before_held_nodes(e)]
        if before:
            # Hollow: scored before held nodes were prescribed, so lower than the rest would show.
            ax.plot(*zip(*before, strict=True), "o", color="white", markeredgecolor=line.get_color(), zorder=3)
        named = [
            f" ({marked(e)})" if e.name != base and not e.name.startswith(f"{base}-n") else mark(e) for e in points
        ]
        lines.append(
            f"| `{base}` | " + ", ".join(f"{x:,} → {y:.2f}{n}" for x, y, n in zip(xs, ys, named, strict=True)) + " |"
        )
    ax.set_xscale("log", base=2)
    labels = ("training samples", "DCM (%), volume form, scored samples", "Accuracy against training data")
    save(fig, ax, path, labels, legend_size=7)
    return lines


def ceiling_figure(entries: list[Entry], path: Path) -> list[str]:
    """The POD bases' own ceiling against M (figure and table lines); empty without a POD model."""
    curves: dict[str, dict[int, float]] = {}
    for e in entries:
        points = {int(k[len(CEILING_PREFIX) :]): v for k, v in e.metrics.items() if k.startswith(CEILING_PREFIX)}
        if points:
            curves[e.name] = dict(sorted(points.items()))
    served = {name: next(e for e in entries if e.name == name).metrics["dcm_combined"] for name in curves}
    # Models sharing a basis (the same POD truncated to their M) draw one curve.
    for name in list(curves):
        if any(curves[other] == curves[name] for other in curves if other < name):
            del curves[name]
    if not curves:
        return []
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for name, points in curves.items():
        ax.plot(list(points), list(points.values()), marker="o", label=f"{name}: best M-term approximation")
    for (name, dcm), style in zip(served.items(), ("--", ":", "-."), strict=False):
        ax.axhline(dcm, linestyle=style, linewidth=1, color="grey", label=f"{name} served ({dcm:.1f} %)")
    ax.set_xscale("log", base=2)
    labels = (
        "modes M",
        "DCM (%), volume form, test split, all samples",
        "What a POD basis of M modes can represent at best",
    )
    save(fig, ax, path, labels, legend_size=7)
    modes = sorted({m for points in curves.values() for m in points})
    lines = ["| basis | " + " | ".join(f"M = {m}" for m in modes) + " |", "|---" * (1 + len(modes)) + "|"]
    for name, points in curves.items():
        lines.append(f"| `{name}` | " + " | ".join(f"{points[m]:.2f}" if m in points else "–" for m in modes) + " |")
    return lines


def regime_baselines(nak: Path, data: Path, mesh: Path, entries: list[Entry], regime: str) -> dict[str, dict[str, Any]]:
    """The Kelvinlet at 5 cm and at every ε a model of `regime` was fitted to, green-linear and, for the
    nonlinear regime, green-tangent: on the test split of the linear `data`, on all of the nonlinear
    `data` (a held-out set of another seed, as the nonlinear networks are scored)."""
    suffix = " — nonlinear" if regime == "nonlinear" else ""
    split = "all" if regime == "nonlinear" else "test"
    fitted = sorted({e.epsilon for e in entries if e.regime == regime and e.method != "base" and e.epsilon != 0.05})
    baselines = {f"Kelvinlet ε = 5 cm (nak){suffix}": baseline(nak, data, mesh, "kelvinlet", 0.05, split)}
    for eps in fitted:
        baselines[f"Kelvinlet ε = {eps * 100:g} cm (nak){suffix}"] = baseline(nak, data, mesh, "kelvinlet", eps, split)
    baselines[f"green-linear (exact linear FEM){suffix}"] = baseline(nak, data, mesh, "green-linear", None, split)
    if regime == "nonlinear":
        baselines[f"green-tangent (linearized at the preload){suffix}"] = baseline(
            nak, data, mesh, "green-tangent", None, split
        )
    return baselines


def write_report(
    data: Path, models: list[Path], nak: Path, mesh: Path, out: Path, nonlinear_data: Path | None = None
) -> None:
    entries = read_models(models)
    linear = regime_baselines(nak, data, mesh, entries, "linear")
    nonlinear = regime_baselines(nak, nonlinear_data, mesh, entries, "nonlinear") if nonlinear_data else {}
    out.mkdir(parents=True, exist_ok=True)
    figure(entries, {**linear, **nonlinear}, out / "accuracy-latency.png")
    ceiling = ceiling_figure(entries, out / "basis-ceiling.png")
    curve = learning_curve(entries, out / "learning-curve.png")
    rows = [
        "| model | regime | method | prior | trained on | ε (cm) | DCM single | DCM multi | DCM all | code form all | "
        "network ms p50 | total ms p50 |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for e in sorted(entries, key=lambda e: (e.regime, e.name)):
        m = e.metrics
        rows.append(
            f"| {marked(e)} | {e.regime} | {METHOD_LABEL[e.method]} | {e.prior if e.method == 'res' else '–'} | "
            f"{e.trained_on} | {e.epsilon * 100:g} | "
            f"{m.get('dcm_single', float('nan')):.2f} | {m.get('dcm_multi', float('nan')):.2f} | "
            f"{m['dcm_combined']:.2f} | {m['dcm_code_combined']:.2f} | {m.get('network_ms_p50', float('nan')):.3f} | "
            f"{m.get('total_ms_p50', float('nan')):.3f} |"
        )
    text = [
        "# Trained networks on the phantom liver",
        "",
        "Generated by `scripts/train-all` (its last step, `scripts/nak-train report`) from the manifests in",
        "`models/phantom-liver/` (served), `models/phantom-liver/table2/` and `table3/` (trained on one subset,",
        "at the paper's ε, or not the best of their method; scored, not served) and `reduced/`. Their",
        "`[metrics]` come from `nak eval` on the test split (nonlinear ones: on the held-out set below); the",
        "baselines are scored by `nak eval` when the page is made. Times: the serving engine's time per",
        "request (`nak eval`: about 200 requests spread over the split, one at a time) on this machine's 2 vCPUs.",
        "Every score is of the field as nak serves it, whose held nodes answer their grasp's displacement",
        "exactly (docs/design.md §7); \\*: scored before nak did so (2026-12-07), on a model that ships no graph",
        "to score again (hollow in the learning curve).",
        f"Linear dataset: `{data}` (`nak datagen --regime linear --preset paper --seed 0`).",
    ]
    if nonlinear_data:
        held_out = open_dataset(nonlinear_data).info
        text += [
            "Nonlinear networks: trained on the paper-size set (`nak datagen --regime nonlinear --preset paper",
            "--seed 0`; those named `*-more-nl` also on two more sets of other seeds, docs/training.md) and",
            "scored, like the nonlinear baselines, on every converged sample of a held-out set of",
            f"a seed training never saw, `{nonlinear_data}` (`nak datagen --regime nonlinear --single",
            f"{held_out['single']} --multi {held_out['multi']} --seed {held_out['seed']}`; failed solves left out).",
        ]
    text += [
        "",
        "## Linear regime: DCM in the paper's code form (comparable with its Table 2)",
        "",
        "Indiv.: trained and tested on single-grasper samples; Comb.: two-grasper; Multi: one model",
        "trained on both, tested on all. `–`: not trained.",
        "",
        *table(entries, "dcm_code", linear, with_paper=True),
        "",
        "## Linear regime: DCM as docs/design.md §6 defines it (volume-weighted mean of relative errors)",
        "",
        *table(entries, "dcm", linear, with_paper=False),
        "",
    ]
    if nonlinear_data:
        text += [
            "## Nonlinear regime: DCM in the paper's code form (comparable with its Table 3)",
            "",
            "Models trained on all samples (Multi) only; `–`: not trained.",
            "",
            *table(entries, "dcm_code", nonlinear, with_paper=True, regime="nonlinear"),
            "",
            "## Nonlinear regime: DCM as docs/design.md §6 defines it",
            "",
            *table(entries, "dcm", nonlinear, with_paper=False, regime="nonlinear"),
            "",
        ]
    text += [
        "## Every model",
        "",
        *rows,
        "",
        "## Accuracy against served time",
        "",
        "![DCM against the engine's time per request](models/accuracy-latency.png)",
        "",
    ]
    if ceiling:
        text += [
            "## The reduced bases' ceiling",
            "",
            "DCM (volume form) of the best M-term approximation of each test target by the POD basis",
            "(for +Res the residual u_true − prior, scored against u_true, so it is the served field's best):",
            "what any encoder over that basis can reach. Grey lines: what the trained encoders reach. A",
            'network trained with `holdout = "val"` (its test split trained too) is measured on its 256 val',
            "samples instead.",
            "",
            *ceiling,
            "",
            "![POD ceiling against M](models/basis-ceiling.png)",
            "",
        ]
    if curve:
        text += [
            "## Accuracy against training data",
            "",
            "The same configuration trained on fewer samples spread over the train split",
            "(`scripts/nak-train all --config C --train-samples N`; their manifests in `table3/curve/`), and",
            "on more (`scripts/nak-train train --more-data DIR…`; the model's name beside its point):",
            "",
            *curve,
            "",
            "![DCM against training samples](models/learning-curve.png)",
            "",
        ]
    (out.parent / "models.md").write_text("\n".join(text))
    print(f"wrote {out.parent / 'models.md'} and {out / 'accuracy-latency.png'}")
