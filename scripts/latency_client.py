"""An independent latency client for nak: Python grpcio, the same calls a simulator written in Python
makes, timed from each request's due time. scripts/latency-report runs it beside `nak bench` so the
load generator's own figures can be checked against a client that shares none of its code.

  python scripts/latency_client.py --target 127.0.0.1:50051 --rate 1000 --duration 5 --out a.json
  python scripts/latency_client.py --target 127.0.0.1:50051 --mode stream --rate 1000 --duration 5

Open loop (`--rate`): requests are due at a constant rate on one connection, one call outstanding at a
time in unary mode (a late answer delays the next request, and that delay counts); closed loop (no
`--rate`): the next call goes out when the last answer arrived. Each request holds two graspers of ten
nodes (grasp regions 3 and 8), K = 20, the size the paper's two-grasper requests have on average.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "examples"))
import client  # noqa: E402

# The largest HTTP/2 frame: a full field (116 kB) arrives in one DATA frame instead of eight.
MAX_FRAME_SIZE = (1 << 24) - 1


def wait_until(due: float) -> None:
    """Sleeps to 200 µs before `due` (time.sleep overshoots by tens of µs) and spins the rest."""
    ahead = due - time.perf_counter() - 200e-6
    if ahead > 0:
        time.sleep(ahead)
    while time.perf_counter() < due:
        pass


def percentiles(us: list[float]) -> dict[str, float]:
    a = np.asarray(us)
    return {
        "p50": float(np.percentile(a, 50)),
        "p90": float(np.percentile(a, 90)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
    }


def run_unary(
    stub: Any, request: Any, rate: float | None, warmup: float, duration: float
) -> tuple[list[float], list[float]]:
    latency: list[float] = []
    server: list[float] = []
    start = time.perf_counter() + 0.05
    end = start + warmup + duration
    k = 0
    while True:
        due = start + k / rate if rate else time.perf_counter()
        if due >= end:
            break
        if rate:
            wait_until(due)
        response = stub.Predict(request)
        done = time.perf_counter()
        if due >= start + warmup:
            latency.append((done - due) * 1e6)
            server.append(response.timing.total_us)
        k += 1
    return latency, server


def run_stream(stub: Any, request: Any, rate: float, warmup: float, duration: float) -> tuple[list[float], list[float]]:
    start = time.perf_counter() + 0.05
    end = start + warmup + duration
    due_times: collections.deque[float] = collections.deque()
    lock = threading.Lock()

    def requests() -> Iterator[Any]:
        k = 0
        while (due := start + k / rate) < end:
            wait_until(due)
            with lock:
                due_times.append(due)
            yield request
            k += 1

    latency: list[float] = []
    server: list[float] = []
    for response in stub.PredictStream(requests()):
        done = time.perf_counter()
        with lock:
            due = due_times.popleft()
        if due >= start + warmup:
            latency.append((done - due) * 1e6)
            server.append(response.timing.total_us)
    return latency, server


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--target", default="127.0.0.1:50051")
    parser.add_argument("--mode", choices=["unary", "stream"], default="unary")
    parser.add_argument("--rate", type=float, help="requests per second (open loop); absent: closed loop")
    parser.add_argument("--duration", type=float, default=5.0, help="measured seconds")
    parser.add_argument("--warmup", type=float, default=1.0, help="seconds sent before measuring")
    parser.add_argument(
        "--default-frames", action="store_true", help="keep gRPC's 16 KiB HTTP/2 frames (default: the largest)"
    )
    parser.add_argument("--out", type=Path, help="write the result as JSON here")
    args = parser.parse_args()
    if args.mode == "stream" and not args.rate:
        parser.error("stream mode needs --rate")

    pb, rpc = client.load_stubs()
    options = [] if args.default_frames else [("grpc.http2.max_frame_size", MAX_FRAME_SIZE)]
    options.append(("grpc.max_receive_message_length", 64 << 20))
    with grpc.insecure_channel(args.target, options=options) as channel:
        stub = rpc.DeformationStub(channel)
        mesh = stub.GetMesh(pb.GetMeshRequest())
        request = pb.PredictRequest(model="kelvinlet", grasps=client.two_graspers(pb, mesh))
        if args.mode == "unary":
            latency, server = run_unary(stub, request, args.rate, args.warmup, args.duration)
        else:
            latency, server = run_stream(stub, request, args.rate, args.warmup, args.duration)
    result = {
        "client": f"python grpcio {grpc.__version__}",
        "mode": args.mode,
        "rate_rps": args.rate,
        "requests": len(latency),
        "latency_us": percentiles(latency),
        "server_us": percentiles(server),
    }
    print(
        f"{result['client']}, {args.mode}, {'closed loop' if not args.rate else f'{args.rate:.0f}/s'}: "
        f"{len(latency)} answers; latency p50 {result['latency_us']['p50']:.0f} µs, "
        f"p99 {result['latency_us']['p99']:.0f} µs; server p50 {result['server_us']['p50']:.0f} µs"
    )
    if args.out:
        args.out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
