"""Starting a local `nak serve` for the measurement scripts (reliability, latency report)."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path


def start(command: list[str], log_path: Path, timeout_s: float = 60.0) -> subprocess.Popen[bytes]:
    """Runs `command` (a `nak serve --log-format json ...` line) with its log in `log_path` and
    returns once the server says it is listening."""
    with log_path.open("w") as log:
        process = subprocess.Popen(command, stderr=log)
    deadline = time.monotonic() + timeout_s
    while '"listening"' not in log_path.read_text():
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            raise SystemExit(f"nak serve did not start: see {log_path}")
        time.sleep(0.1)
    return process
