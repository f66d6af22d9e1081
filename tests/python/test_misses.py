"""Where a network misses: nak eval's per-sample errors joined with each sample's push and solve."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from nak_training.errors import TrainingInputError
from nak_training.failures import Outcome
from nak_training.misses import Miss, misses, report, table

BOX = Path(__file__).resolve().parents[2] / "tests/fixtures/box.msh"


def test_each_group_holds_its_samples_and_its_share_of_the_error() -> None:
    found = [
        Miss("single", 0.1, Outcome(0, -5.0, False, "")),
        Miss("multi", 0.3, Outcome(1, 30.0, False, "")),
        Miss("single", 0.6, Outcome(2, 70.0, False, "", branch_jumps=2)),
    ]
    rows = {line.split(" | ")[0].lstrip("| "): line for line in table(found).splitlines()[2:]}
    # Pulls: one single-grasper sample at 10 % error, a tenth of the summed error.
    assert rows["pulls (push < 0 mm)"] == "| pulls (push < 0 mm) | 1 | 90.0 | 0 | – | 1 | 90.0 | 10 % |"
    assert rows["push 20–40 mm"].endswith("| 0 | – | 1 | 70.0 | 1 | 70.0 | 30 % |")
    assert rows["all"] == "| all | 2 | 65.0 | 1 | 70.0 | 3 | 66.7 | 100 % |"
    assert rows["solve undid a load step (branch jump)"].endswith("| 1 | 40.0 | 60 % |")
    assert rows["solve undid no load step"].endswith("| 2 | 80.0 | 40 % |")


def test_a_report_without_per_sample_errors_or_with_unknown_samples_is_refused() -> None:
    with pytest.raises(TrainingInputError, match="no per-sample errors"):
        misses({"data": "d", "samples": []}, {})
    with pytest.raises(TrainingInputError, match="not in the dataset"):
        misses({"data": "d", "samples": [{"index": 7, "subset": "single", "volume": 0.1}]}, {})


def test_the_prior_on_a_nonlinear_set_is_tabulated_and_drawn(nak_binary: Path, tmp_path: Path) -> None:
    data = tmp_path / "data"
    args = ["datagen", "--mesh", str(BOX), "--regime", "nonlinear", "--single", "6", "--multi", "0", "--seed", "0"]
    args += ["--cache-dir", str(tmp_path / "cache"), "--out", str(data)]
    subprocess.run([str(nak_binary), *args], check=True, capture_output=True)
    picture = tmp_path / "misses.png"
    text = report(data, "kelvinlet", nak_binary, BOX, picture)
    # The box has one grasp region: single-grasper samples only.
    assert "| all | 6 | " in text and " | 0 | – | 6 | " in text
    assert picture.stat().st_size > 10_000
    with pytest.raises(TrainingInputError, match="not a model directory"):
        report(data, str(tmp_path / "nowhere"), nak_binary, BOX, None)
