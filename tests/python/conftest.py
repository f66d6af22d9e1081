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
sys.path.insert(0, str(ROOT / "organ"))
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
    with start_server_ports(nak_binary, extra_args, []) as addresses:
        yield addresses["listening"]


@contextmanager
def start_server_ports(nak_binary: Path, extra_args: list[str], side_ports: list[str]) -> Iterator[dict[str, str]]:
    """`nak serve` as in `start_server`, waiting also for the side ports it logs (e.g. "viewer listening");
    yields each log message's address, "listening" being the gRPC port."""
    proc = subprocess.Popen(
        [str(nak_binary), "serve", "--listen", "127.0.0.1:0", "--log-format", "json", *extra_args],
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stderr is not None
    wanted = {"listening", *side_ports}
    addresses: dict[str, str] = {}
    for line in proc.stderr:
        fields = json.loads(line)["fields"]
        if fields.get("message") in wanted:
            addresses[fields["message"]] = fields["address"]
            if wanted <= addresses.keys():
                break
    if not wanted <= addresses.keys():
        proc.kill()
        pytest.fail(f"nak serve exited before logging {sorted(wanted - addresses.keys())}")
    try:
        yield addresses
    finally:
        proc.terminate()
        proc.wait(timeout=10)


@pytest.fixture()
def nak_server(nak_binary: Path) -> Iterator[str]:
    """`nak serve` on the embedded phantom."""
    with start_server(nak_binary, []) as address:
        yield address
