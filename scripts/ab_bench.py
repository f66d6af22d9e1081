"""Compare two builds of a criterion benchmark on a noisy, shared machine: run them alternately.

Run after run, this host's speed drifts by more than the changes worth measuring (10–30 % between
sessions, several percent within minutes), so one run of each build, or criterion's `--baseline`
against a run taken minutes earlier, can report a gain or a loss that is only drift. Alternating the
two binaries, each run short, pairs every run of one with a neighbouring run of the other; the median
of the per-pair ratios and the count of pairs each side won survive the drift.

Build the two binaries first, for example:

    git stash; cargo bench --bench prior --no-run; cp target/release/deps/prior-<hash> /tmp/before
    git stash pop; cargo bench --bench prior --no-run; cp target/release/deps/prior-<hash> /tmp/after
    python3 scripts/ab_bench.py /tmp/before /tmp/after 'prior/solve/20$' --rounds 10 --cpu 1
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
from pathlib import Path

# criterion's summary line: "name   time:   [low unit estimate unit high unit]"
TIME = re.compile(r"time:\s+\[\S+ \S+ (\S+) (ns|µs|us|ms|s) ")
SCALE_US = {"ns": 1e-3, "µs": 1.0, "us": 1.0, "ms": 1e3, "s": 1e6}


def estimate_us(binary: Path, benchmark: str, cpu: int | None, seconds: float) -> float:
    """criterion's point estimate (µs) of the one benchmark matching `benchmark` in one short run."""
    command = [str(binary), "--bench", benchmark, "--warm-up-time", "1"]
    command += ["--measurement-time", str(seconds), "--noplot"]
    if cpu is not None:
        command = ["taskset", "-c", str(cpu)] + command
    output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    found = TIME.findall(output)
    if len(found) != 1:
        raise SystemExit(f"{benchmark!r} matched {len(found)} benchmarks in {binary}; it must match one")
    value, unit = found[0]
    return float(value) * SCALE_US[unit]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("before", type=Path, help="the reference build's criterion bench binary")
    parser.add_argument("after", type=Path, help="the changed build's criterion bench binary")
    parser.add_argument("benchmark", help="a criterion filter (a regex) that matches one benchmark")
    parser.add_argument("--rounds", type=int, default=10, help="pairs of runs [default: 10]")
    parser.add_argument("--cpu", type=int, help="pin both to this CPU (taskset)")
    parser.add_argument("--seconds", type=float, default=2.0, help="measurement time of each run")
    args = parser.parse_args()
    before, after = [], []
    for round_number in range(1, args.rounds + 1):
        before.append(estimate_us(args.before, args.benchmark, args.cpu, args.seconds))
        after.append(estimate_us(args.after, args.benchmark, args.cpu, args.seconds))
        print(f"round {round_number:>2}: before {before[-1]:10.3f} µs   after {after[-1]:10.3f} µs", flush=True)
    ratios = [b / a for a, b in zip(before, after, strict=True)]
    won = sum(r < 1.0 for r in ratios)
    print(f"median       before {statistics.median(before):10.3f} µs   after {statistics.median(after):10.3f} µs")
    print(
        f"after/before median of the paired ratios {statistics.median(ratios):.3f}; after faster in {won} of {len(ratios)}"
    )


if __name__ == "__main__":
    main()
