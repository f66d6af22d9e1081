"""Two models compared sample by sample: their DCMs, the gain and its paired standard error."""

from __future__ import annotations

import math
import subprocess
from pathlib import Path
from typing import Any

import pytest
from nak_training.errors import TrainingInputError
from nak_training.paired import paired, report

BOX = Path(__file__).resolve().parents[2] / "tests/fixtures/box.msh"


def evaluated(errors: dict[int, tuple[str, float]]) -> dict[str, Any]:
    return {"data": "d", "samples": [{"index": i, "subset": s, "volume": e} for i, (s, e) in errors.items()]}


def test_the_gain_is_the_mean_per_sample_difference_with_its_paired_error() -> None:
    first = evaluated({0: ("single", 0.30), 1: ("single", 0.10), 2: ("multi", 0.50), 3: ("multi", 0.20)})
    second = evaluated({0: ("single", 0.20), 1: ("single", 0.10), 2: ("multi", 0.40), 3: ("multi", 0.20)})
    rows = {r.subset: r for r in paired(first, second)}
    assert (rows["single"].first, rows["single"].second) == pytest.approx((80.0, 85.0))
    # Gains 10, 0, 10, 0 points: mean 5, sample deviation 5.77, over √4.
    assert rows["all"].gain == pytest.approx(5.0)
    assert rows["all"].error == pytest.approx(math.sqrt(100 / 3) / 2)
    assert rows["multi"].samples == 2 and rows["multi"].gain == pytest.approx(5.0)
    with pytest.raises(TrainingInputError, match=r"scored different samples \(e.g. \[3\]\)"):
        paired(first, evaluated({0: ("single", 0.2), 1: ("single", 0.1), 2: ("multi", 0.4)}))
    with pytest.raises(TrainingInputError, match="no per-sample errors"):
        paired(first, {"data": "d", "samples": []})


def test_two_served_models_are_compared_through_nak_eval(nak_binary: Path, tmp_path: Path) -> None:
    data = tmp_path / "data"
    args = ["datagen", "--mesh", str(BOX), "--regime", "nonlinear", "--single", "6", "--multi", "0", "--seed", "0"]
    args += ["--cache-dir", str(tmp_path / "cache"), "--out", str(data)]
    subprocess.run([str(nak_binary), *args], check=True, capture_output=True)
    text = report(data, ["kelvinlet", "green-linear"], nak_binary, BOX, "all")
    assert text.splitlines()[0].startswith("| samples | n | kelvinlet DCM % | green-linear DCM % |")
    assert "| all | 6 | " in text
    with pytest.raises(TrainingInputError, match="compares two models; got 1"):
        report(data, ["kelvinlet"], nak_binary, BOX, "all")
