"""The nonlinear failure report: grasps' inward push from the dataset's own normals, failures binned by it."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
from nak_training.failures import EDGES_MM, Outcome, failure_bins, inward_push_mm, outcomes, report, why

BOX = Path(__file__).resolve().parents[2] / "tests/fixtures/box.msh"


def test_a_push_along_the_inward_normal_counts_positive_and_a_pull_negative() -> None:
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [0.0, 0.0, 0.0]])
    assert inward_push_mm(normals, [0], [0.0, 0.0, -0.03]) == pytest.approx(30.0)
    assert inward_push_mm(normals, [0, 1], [0.0, 0.0, 0.02]) < 0
    with pytest.raises(ValueError, match="no outward normal"):
        inward_push_mm(normals, [2], [0.0, 0.0, 0.01])


def test_failures_are_binned_by_the_deepest_push() -> None:
    found = [
        Outcome(0, -5.0, False, ""),
        Outcome(1, 10.0, True, "x"),
        Outcome(2, 45.0, True, "y"),
        Outcome(3, 90.0, False, ""),
    ]
    bins = failure_bins(found)
    assert [b.samples for b in bins] == [1, 1, 0, 1, 1]
    assert [b.failed for b in bins] == [0, 1, 0, 1, 0]
    assert len(bins) == len(EDGES_MM) - 1 and bins[1].rate == 1.0 and bins[2].rate == 0.0
    assert why(
        "no equilibrium at load step 3 (load fraction 0.5000): an element inverted (J ≤ 0); residual history (N) []"
    ) == ("an element inverted (J ≤ 0)")


def test_a_crippled_nonlinear_set_reports_every_sample_failed_with_its_reason(nak_binary: Path, tmp_path: Path) -> None:
    def datagen(out: Path, *extra: str) -> None:
        args = ["datagen", "--mesh", str(BOX), "--regime", "nonlinear", "--single", "6", "--multi", "0"]
        args += ["--chunk-size", "3", "--seed", "0", "--cache-dir", str(tmp_path / "cache"), "--out", str(out)]
        subprocess.run([str(nak_binary), *args, *extra], check=True, capture_output=True)

    datagen(tmp_path / "warm")  # caches the gravity preload, which the crippled run could not solve
    data = tmp_path / "data"
    datagen(data, "--max-newton-iterations", "1", "--max-step-cuts", "0")
    found = outcomes(data)
    assert sorted(o.index for o in found) == list(range(6))
    assert all(o.failed and o.reason for o in found)
    assert not any("residual history" in o.reason for o in found)
    text = report(data)
    assert "| all | 6 | 6 | 100.0 % |" in text
