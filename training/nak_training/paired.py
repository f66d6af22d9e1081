"""Two models on the same samples: how far apart their DCMs are, with the paired standard error.

A model's DCM on 1,000 held-out samples carries a standard error of about a point, most of it which
samples are hard, and two models share that: the spread of their per-sample differences is a fraction
of it, so a difference of half a point can be told from noise on one set where the two scores' own
errors overlap.

python -m nak_training paired --data HELD_OUT --model A B [--split all]
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import TrainingInputError
from .evaluate import sample_errors, scored

SUBSETS = ("single", "multi")


@dataclass(frozen=True)
class Difference:
    subset: str
    samples: int
    first: float  # DCM %, volume form
    second: float
    gain: float  # second − first, points
    error: float  # its paired standard error, points


def errors_of(report: dict[str, Any]) -> dict[int, tuple[str, float]]:
    """Each scored sample's subset and volume-form relative error in a `nak eval` JSON report."""
    return {int(s["index"]): (str(s["subset"]), float(s["volume"])) for s in sample_errors(report)}


def paired(first: dict[str, Any], second: dict[str, Any]) -> list[Difference]:
    """Per subset and over all samples, the two reports' DCMs and the second's gain over the first with
    its paired standard error. Both must have scored the same samples."""
    a, b = errors_of(first), errors_of(second)
    if a.keys() != b.keys():
        only = sorted(a.keys() ^ b.keys())
        raise TrainingInputError(
            Path(str(second.get("data"))), f"the two reports scored different samples (e.g. {only[:5]})"
        )
    rows = []
    for subset in (*SUBSETS, "all"):
        keys = [k for k in sorted(a) if subset in ("all", a[k][0])]
        if not keys:
            continue
        x, y = np.array([a[k][1] for k in keys]), np.array([b[k][1] for k in keys])
        gain = 100 * (x - y)
        error = float(gain.std(ddof=1) / math.sqrt(len(keys))) if len(keys) > 1 else math.nan
        rows.append(Difference(subset, len(keys), 100 * (1 - x.mean()), 100 * (1 - y.mean()), gain.mean(), error))
    return rows


def table(names: tuple[str, str], rows: list[Difference]) -> str:
    lines = [
        f"| samples | n | {names[0]} DCM % | {names[1]} DCM % | gain (points) ± paired s.e. |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r.subset} | {r.samples} | {r.first:.2f} | {r.second:.2f} | {r.gain:+.2f} ± {r.error:.2f} |")
    return "\n".join(lines)


def report(data: Path, models: list[str], nak: Path, mesh: Path, split: str) -> str:
    """Scores two models (model directories, or models nak serves by name) on `split` of `data` and
    tabulates the second's gain over the first, sample by sample."""
    if len(models) != 2:
        raise TrainingInputError(data, f"paired compares two models; got {len(models)}")
    (name_a, first), (name_b, second) = (scored(m, data, nak, mesh, split) for m in models)
    return table((name_a, name_b), paired(first, second))
