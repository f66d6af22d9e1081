"""Shared fixtures: paths in the repository and a running `nak serve`."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "examples"))
sys.path.insert(0, str(ROOT / "models" / "phantom-liver"))
sys.path.insert(0, str(ROOT / "training"))


@pytest.fixture(scope="session")
def nak_binary() -> Path:
    """The debug binary built by `cargo test` (override with NAK_BIN)."""
    path = Path(os.environ.get("NAK_BIN", ROOT / "target" / "debug" / "nak")).resolve()
    if not path.exists():
        pytest.fail(f"{path} not found: run `cargo build` first (scripts/test does)")
    return path


@contextmanager
def start_server(nak_binary: Path, extra_args: list[str]) -> Iterator[str]:
    """`nak serve` at a free loopback port with `extra_args`; yields host:port, stops it with SIGTERM."""
    proc = subprocess.Popen(
        [str(nak_binary), "serve", "--listen", "127.0.0.1:0", "--log-format", "json", *extra_args],
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stderr is not None
    address = None
    for line in proc.stderr:
        record = json.loads(line)
        if record["fields"].get("message") == "listening":
            address = record["fields"]["address"]
            break
    if address is None:
        proc.kill()
        pytest.fail("nak serve exited before listening")
    try:
        yield address
    finally:
        proc.terminate()
        proc.wait(timeout=10)


@pytest.fixture()
def nak_server(nak_binary: Path) -> Iterator[str]:
    """`nak serve` on the embedded phantom."""
    with start_server(nak_binary, []) as address:
        yield address
