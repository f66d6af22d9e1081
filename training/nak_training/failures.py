"""Where nonlinear ground truth fails: each sample's deepest inward push (the grasp displacement along
the inward surface normal, mm, the largest over its graspers) and the failure rate in bins of it. A
surface patch pushed centimetres into the organ compresses the tissue beneath it hardest, and that is
where Newton stalls (docs/finite-elements.md, "The paper-size set").
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .dataset import is_failed, open_dataset, read_json
from .errors import TrainingInputError

# Bin edges (mm) of the deepest inward push; a pull has a negative push.
EDGES_MM = (-np.inf, 0.0, 20.0, 40.0, 60.0, np.inf)


@dataclass(frozen=True)
class Outcome:
    index: int
    push_mm: float
    failed: bool
    reason: str
    # Load steps the solver undid because they ended on another equilibrium branch.
    branch_jumps: int = 0


@dataclass(frozen=True)
class Bin:
    low_mm: float
    high_mm: float
    samples: int
    failed: int

    @property
    def rate(self) -> float:
        return self.failed / self.samples if self.samples else 0.0


def inward_push_mm(normals: np.ndarray, nodes: list[int], displacement: list[float]) -> float:
    """How far a grasp moves its nodes into the organ: −d · n̂ for the mean outward normal n̂ of its nodes."""
    mean = normals[nodes].mean(axis=0)
    length = float(np.linalg.norm(mean))
    if length == 0.0:
        raise ValueError(f"grasp nodes {nodes} have no outward normal: not surface nodes")
    return -1e3 * float(np.dot(displacement, mean / length))


def why(failure: str) -> str:
    """The reason in a solver failure ("no equilibrium at load step S (load fraction F): REASON; residual
    history …")."""
    after = failure.split(": ", 1)[-1]
    return after.split("; residual history")[0]


def outcomes(root: Path) -> list[Outcome]:
    """Every solved sample of the dataset at `root`, with its deepest inward push and whether it failed."""
    dataset = open_dataset(root)
    normals = dataset.mesh.normals.numpy()
    found = []
    for path in sorted(root.glob("chunk-*.json")):
        for record in read_json(path):
            try:
                pushes = [inward_push_mm(normals, g["nodes"], g["displacement"]) for g in record["grasps"]]
            except (KeyError, TypeError, ValueError, IndexError) as e:
                raise TrainingInputError(path, f"sample {record.get('index')}: malformed grasps ({e})") from e
            failure = str(record["solver"]["failure"]) if is_failed(record) else None
            jumps = int((record.get("solver") or {}).get("branch_jumps", 0))
            found.append(Outcome(int(record["index"]), max(pushes), failure is not None, why(failure or ""), jumps))
    if not found:
        raise TrainingInputError(root, "no generated chunks")
    return found


def failure_bins(found: list[Outcome], edges: tuple[float, ...] = EDGES_MM) -> list[Bin]:
    """The failure rate in each bin [low, high) of the deepest inward push."""
    return [
        Bin(
            low,
            high,
            sum(low <= o.push_mm < high for o in found),
            sum(low <= o.push_mm < high and o.failed for o in found),
        )
        for low, high in zip(edges, edges[1:], strict=False)
    ]


def span(low_mm: float, high_mm: float) -> str:
    """A bin of the deepest inward push as a table row names it."""
    if low_mm == -np.inf:
        return f"< {high_mm:g} (pulls)"
    if high_mm == np.inf:
        return f"≥ {low_mm:g}"
    return f"{low_mm:g}–{high_mm:g}"


def report(root: Path) -> str:
    found = outcomes(root)
    lines = ["| deepest inward push (mm) | samples | failed | rate |", "|---|---|---|---|"]
    for b in failure_bins(found):
        lines.append(f"| {span(b.low_mm, b.high_mm)} | {b.samples} | {b.failed} | {100 * b.rate:.1f} % |")
    failed = [o for o in found if o.failed]
    lines.append(f"| all | {len(found)} | {len(failed)} | {100 * len(failed) / len(found):.1f} % |")
    for o in failed:
        lines.append(f"- sample {o.index}: push {o.push_mm:.1f} mm, {o.reason}")
    return "\n".join(lines)
