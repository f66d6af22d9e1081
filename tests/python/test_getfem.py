"""nak's nonlinear ground truth equals an independent getFEM solve (scripts/getfem-check), on one
single- and one two-grasper sample of the coarse phantom: about 20 s on two cores.

getFEM is Debian's python3-getfem for the system Python (scripts/setup-getfem, which scripts/test runs,
installs it); without it this test fails rather than skips. The samples are made by the release binary,
which scripts/test builds before the Python tests (scripts/warm-cache): the debug build takes about a
minute for the one single-grasper sample alone.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SYSTEM_PYTHON = "/usr/bin/python3"


def test_nonlinear_fields_equal_getfem_on_the_coarse_phantom() -> None:
    found = subprocess.run([SYSTEM_PYTHON, "-c", "import getfem"], capture_output=True, text=True)
    if found.returncode != 0:
        pytest.fail(f"{SYSTEM_PYTHON} cannot import getfem: run scripts/setup-getfem\n{found.stderr}")
    nak = ROOT / "target" / "release" / "nak"
    if not nak.exists():
        pytest.fail(f"{nak} not found: cargo build --release --bin nak (scripts/test does)")
    args = ["--single", "1", "--multi", "1", "--seed", "0", "--nak", str(nak)]
    done = subprocess.run(
        [SYSTEM_PYTHON, str(ROOT / "scripts" / "getfem_check.py"), *args], capture_output=True, text=True, timeout=600
    )
    report = done.stdout + done.stderr
    assert done.returncode == 0, report
    assert "2 samples compared, 0 failed in nak, 0 not solved by getFEM" in report, report
    # Each sample's row: its relative L2 differences (volume-weighted, nodal) within the tolerance.
    rows = re.findall(
        r"^\| (\d+) \| (single|multi) \|.*\| ([0-9.e+-]+) \| ([0-9.e+-]+) \| [0-9.e+-]+ \| \d+ of \d+ \| [0-9.e+-]+ \|$",
        report,
        re.M,
    )
    assert [(index, subset) for index, subset, *_ in rows] == [("0", "single"), ("1", "multi")], report
    assert all(float(weighted) < 1e-6 and float(nodal) < 1e-6 for *_, weighted, nodal in rows), report
    assert re.search(r"^preload: nak's .* relative L2 [0-9.e+-]+ volume-weighted", report, re.M), report
