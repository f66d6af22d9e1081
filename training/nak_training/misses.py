"""Where a network misses: each sample's relative error as nak serves the network (`nak eval`'s
per-sample errors) against how deep its grasps push into the organ, by bins of the deepest inward push
(the bins of the failure table) and the number of graspers, and apart for the samples whose solve
undid a load step that jumped to another equilibrium branch; with the share of the whole error each
group holds, and a figure of every sample.

python -m nak_training misses --data HELD_OUT --model DIR|kelvinlet|green-linear|green-tangent [--figure PNG]
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .errors import TrainingInputError  # noqa: E402
from .evaluate import sample_errors, scored  # noqa: E402
from .failures import EDGES_MM, Outcome, outcomes, span  # noqa: E402

SUBSETS = ("single", "multi")


@dataclass(frozen=True)
class Miss:
    subset: str
    error: float
    solve: Outcome


def misses(report: dict[str, Any], solves: dict[int, Outcome]) -> list[Miss]:
    """The scored samples of a `nak eval` JSON report, each with how its ground truth was solved."""
    try:
        return [Miss(s["subset"], float(s["volume"]), solves[int(s["index"])]) for s in sample_errors(report)]
    except KeyError as e:
        raise TrainingInputError(Path(str(report.get("data"))), f"sample {e} is not in the dataset's chunks") from e


def dcm(errors: list[float]) -> str:
    return f"{100 * (1 - float(np.mean(errors))):.1f}" if errors else "–"


def groups(edges: tuple[float, ...] = EDGES_MM) -> list[tuple[str, Callable[[Outcome], bool]]]:
    """The table's rows: each bin of the deepest inward push, all samples, and the samples whose solve
    undid a branch jump or none."""

    def within(low: float, high: float) -> Callable[[Outcome], bool]:
        return lambda o: low <= o.push_mm < high

    def label(low: float, high: float) -> str:
        return f"pulls (push < {high:g} mm)" if low == -np.inf else f"push {span(low, high)} mm"

    rows = [(label(low, high), within(low, high)) for low, high in zip(edges, edges[1:], strict=False)]
    return [
        *rows,
        ("all", lambda o: True),
        ("solve undid no load step", lambda o: o.branch_jumps == 0),
        ("solve undid a load step (branch jump)", lambda o: o.branch_jumps > 0),
    ]


def table(found: list[Miss]) -> str:
    """Per group of samples: samples and DCM of each subset and of both, and the group's share of the
    summed relative error (where the DCM's shortfall comes from)."""
    total = sum(m.error for m in found) or 1.0  # every sample exact: every share is 0
    lines = [
        "| samples | single | DCM | two graspers | DCM | all | DCM | share of the error |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label, member in groups():
        inside = [m for m in found if member(m.solve)]
        cells = [label]
        for subset in SUBSETS:
            errors = [m.error for m in inside if m.subset == subset]
            cells += [str(len(errors)), dcm(errors)]
        errors = [m.error for m in inside]
        cells += [str(len(errors)), dcm(errors), f"{100 * sum(errors) / total:.0f} %"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def figure(found: list[Miss], name: str, path: Path) -> None:
    """Every sample's relative error against its deepest inward push, one colour per subset; a cross
    where the solve undid a load step that jumped to another equilibrium branch."""
    fig, ax = plt.subplots(figsize=(7, 4))
    for subset, colour, label in (("single", "tab:blue", "one grasper"), ("multi", "tab:orange", "two graspers")):
        for jumped, marker, note in ((False, "o", ""), (True, "x", ", solve undid a branch jump")):
            chosen = [m for m in found if m.subset == subset and (m.solve.branch_jumps > 0) == jumped]
            ax.scatter(
                [m.solve.push_mm for m in chosen],
                [m.error for m in chosen],
                s=14 if jumped else 6,
                alpha=0.9 if jumped else 0.45,
                c=colour,
                marker=marker,
                label=f"{label}{note} ({len(chosen)})",
            )
    ax.axvline(0, color="grey", lw=0.5)
    ax.set_xlabel("deepest inward push of a grasper (mm; < 0: a pull)")
    ax.set_ylabel("relative error ‖u − û‖ / ‖u‖ (L2, volume)")
    ax.set_title(f"{name}: where it misses ({len(found)} samples)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(data: Path, model: str, nak: Path, mesh: Path, figure_path: Path | None) -> str:
    """Scores `model` (a model directory, or a model nak serves by name) on every sample of `data` and
    tabulates where it misses."""
    name, evaluated = scored(model, data, nak, mesh, "all")
    found = misses(evaluated, {o.index: o for o in outcomes(data)})
    if figure_path is not None:
        figure(found, name, figure_path)
    return table(found)
