"""Serving latency before and after a change, measured in one run (scripts/latency-report runs this).

For each server (the `--before` binary, the `--after` one, and the `--after` one with
`--poll-idle-cpus`) a release `nak serve` on the embedded phantom is loaded in turn by `nak bench`
(the after build's) and by the independent Python grpcio client (scripts/latency_client.py): unary at 1,000 requests/s open loop, closed loop on one connection, and
a 1 kHz stream. The before build's own `nak bench` is also run against the after server, to show
what the load generator itself adds. Results go to docs/reports/latency.md and docs/reports/latency/latency.png.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import local_server  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
PORT = 50093


@dataclass(frozen=True)
class Load:
    key: str
    label: str
    bench: list[str]
    python: list[str]


LOADS = [
    Load(
        "unary-1k",
        "unary, 1,000/s open loop",
        ["--mode", "unary", "--concurrency", "4", "--rate", "1000"],
        ["--mode", "unary", "--rate", "1000"],
    ),
    Load(
        "unary-closed",
        "unary, closed loop, 1 connection",
        ["--mode", "unary", "--concurrency", "1"],
        ["--mode", "unary"],
    ),
    Load(
        "stream-1k",
        "stream, 1,000/s",
        ["--mode", "stream", "--concurrency", "1", "--rate", "1000"],
        ["--mode", "stream", "--rate", "1000"],
    ),
]


def nak_bench(binary: Path, load: Load, out: Path, seconds: int, prefix: list[str] | None = None) -> dict[str, Any]:
    subprocess.run(
        (prefix or [])
        + [str(binary), "bench", "--target", f"http://127.0.0.1:{PORT}", "--duration", f"{seconds}s", "--seed", "1"]
        + load.bench
        + ["--output", str(out)],
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    report = json.loads(out.read_text())
    return {
        "latency_us": report["latency_us"],
        "server_us": report["server_us"],
        "server_queue_us": report.get("server_queue_us"),
        "generator_us": report.get("generator_us"),
        "client_cpu_us": report.get("client_cpu_us"),
    }


def python_client(load: Load, out: Path, seconds: int) -> dict[str, Any]:
    subprocess.run(
        [sys.executable, str(ROOT / "scripts/latency_client.py"), "--target", f"127.0.0.1:{PORT}"]
        + ["--duration", str(seconds), "--out", str(out)]
        + load.python,
        check=True,
        stdout=subprocess.DEVNULL,
    )
    result: dict[str, Any] = json.loads(out.read_text())
    return result


@contextmanager
def pinned_pair(cpu_parent: int, cpu_child: int, child: Callable[[], None]) -> Iterator[None]:
    """Runs `child` in a forked process pinned to `cpu_child` while this process, pinned to
    `cpu_parent` for the duration, runs the body; then restores this process's CPUs and waits for
    the child."""
    pid = os.fork()
    if pid == 0:
        try:
            os.sched_setaffinity(0, {cpu_child})
            child()
        finally:
            os._exit(0)
    allowed = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {cpu_parent})
    try:
        yield
    finally:
        os.sched_setaffinity(0, allowed)
        os.waitpid(pid, 0)


def wake_round_trip_us(cpu_a: int, cpu_b: int, rounds: int = 20_000) -> float:
    """Mean round trip (µs) of one byte passed back and forth through two pipes between
    two processes pinned to `cpu_a` and `cpu_b`: each trip wakes the other side twice. On one CPU
    a wake-up is a context switch; across CPUs it is a wake-up of an idle CPU, the cost every
    request pays when its client and server sleep on different cores."""
    to_child, from_parent = os.pipe()
    to_parent, from_child = os.pipe()
    warmup = 500

    def echo() -> None:
        for _ in range(warmup + rounds):
            os.read(to_child, 1)
            os.write(from_child, b"x")

    try:
        with pinned_pair(cpu_a, cpu_b, echo):
            for i in range(warmup + rounds):
                if i == warmup:
                    start = time.perf_counter_ns()
                os.write(from_parent, b"x")
                os.read(to_parent, 1)
            elapsed = time.perf_counter_ns() - start
    finally:
        for fd in (to_child, from_parent, to_parent, from_child):
            os.close(fd)
    return elapsed / rounds / 1e3


# A full answer on the phantom: 9,701 nodes × 3 × f32, and a few bytes of its other fields.
ANSWER_BYTES = 9_701 * 12 + 64
REQUEST_BYTES = 200
FLOOR_ROUNDS = 3_000


def loopback_floor_us(
    cpu_server: int,
    cpu_client: int,
    answer_bytes: int = ANSWER_BYTES,
    unix_socket: bool = False,
    rounds: int = FLOOR_ROUNDS,
) -> float:
    """Median time (µs) for a request of REQUEST_BYTES to cross loopback TCP (or a Unix socket) and
    `answer_bytes` to come back, between two Python processes pinned to `cpu_server` and `cpu_client`,
    one request every millisecond as at 1,000 requests/s: the same bytes as a unary call, without
    HTTP/2, gRPC, the codecs or any computation. Python's own few µs per call on each side make it an
    upper bound of the transport's share of client − server."""
    with tempfile.TemporaryDirectory() as scratch:
        if unix_socket:
            listener = socket.socket(socket.AF_UNIX)
            listener.bind(str(Path(scratch) / "floor.sock"))
            listener.listen(1)
        else:
            listener = socket.create_server(("127.0.0.1", 0))
        address, family = listener.getsockname(), listener.family

        def no_delay(connection: socket.socket) -> None:
            if not unix_socket:
                connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

        def answer_each_request() -> None:
            connection, _ = listener.accept()
            no_delay(connection)
            answer, request = bytes(answer_bytes), bytearray(REQUEST_BYTES)
            while connection.recv_into(request, REQUEST_BYTES, socket.MSG_WAITALL) == REQUEST_BYTES:
                connection.sendall(answer)

        times = []
        with pinned_pair(cpu_client, cpu_server, answer_each_request):
            listener.close()
            with socket.socket(family) as client:
                client.connect(address)
                no_delay(client)
                question, reply = bytes(REQUEST_BYTES), bytearray(answer_bytes)
                warmup = 300
                for i in range(warmup + rounds):
                    time.sleep(0.001)
                    start = time.perf_counter_ns()
                    client.sendall(question)
                    client.recv_into(reply, answer_bytes, socket.MSG_WAITALL)
                    if i >= warmup:
                        times.append(time.perf_counter_ns() - start)
    return statistics.median(times) / 1e3


def transport_floors(across_cpus_only: bool) -> dict[str, float]:
    """`loopback_floor_us` for a full answer and a 1 kB one over TCP and a full one over a Unix socket,
    across the two CPUs and, unless `across_cpus_only`, on one."""
    floors = {
        "full_across_cpus": loopback_floor_us(0, 1),
        "small_across_cpus": loopback_floor_us(0, 1, answer_bytes=1_000),
        "full_unix_across_cpus": loopback_floor_us(0, 1, unix_socket=True),
    }
    if not across_cpus_only:
        floors["full_same_cpu"] = loopback_floor_us(0, 0)
        floors["small_same_cpu"] = loopback_floor_us(0, 0, answer_bytes=1_000)
        floors["full_unix_same_cpu"] = loopback_floor_us(0, 0, unix_socket=True)
    return floors


@dataclass(frozen=True)
class Server:
    key: str
    label: str
    build: str
    flags: list[str]
    colours: tuple[str, str]  # the figure's bars (p50) and dashes (p99)


SERVERS = [
    Server("before", "before", "before", [], ("#c44e52", "#7a1f22")),
    Server("after", "after", "after", [], ("#4c72b0", "#1f3a66")),
    Server("polling", "after, idle CPUs polling", "after", ["--poll-idle-cpus"], ("#55a868", "#2d5e3a")),
]


def cpu_times() -> list[int]:
    """The machine's CPU time so far, by kind, in clock ticks: the first line of /proc/stat."""
    return [int(field) for field in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]


def steal_percent(start: list[int], end: list[int]) -> float:
    """The share of the CPUs' time between two `cpu_times` that the hypervisor gave to other guests
    (steal, the eighth field): how much a shared host disturbed a run."""
    spent = [b - a for a, b in zip(start, end, strict=True)]
    return 100.0 * spent[7] / sum(spent)


def measure(args: argparse.Namespace) -> None:
    data: Path = args.data
    data.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {}
    started = cpu_times()
    for server_kind in SERVERS:
        side = server_kind.key
        binary = args.before if server_kind.build == "before" else args.after
        command = [str(binary), "serve", "--listen", f"127.0.0.1:{PORT}", "--log-format", "json"]
        server = local_server.start(command + server_kind.flags, data / f"server-{side}.log")
        try:
            for load in LOADS:
                print(f"{server_kind.label}: {load.label}", flush=True)
                results[f"{side}/bench/{load.key}"] = nak_bench(
                    args.after, load, data / f"{side}-{load.key}.json", args.seconds
                )
                results[f"{side}/python/{load.key}"] = python_client(
                    load, data / f"{side}-{load.key}-py.json", args.seconds
                )
            if side == "after":
                unary = LOADS[0]
                results["after/old-bench/unary-1k"] = nak_bench(
                    args.before, unary, data / "old-bench.json", args.seconds
                )
            if side == "polling":
                # The server's request holds for the whole machine while it runs.
                results["wake_round_trip_us_polling"] = wake_round_trip_us(0, 1)
                results["floor_us_polling"] = transport_floors(across_cpus_only=True)
        finally:
            server.terminate()
            server.wait(timeout=30)
    # The after server and nak bench both on CPU 0: no wake-up of an idle CPU on either side.
    pin = ["taskset", "-c", "0"]
    command = pin + [str(args.after), "serve", "--listen", f"127.0.0.1:{PORT}", "--log-format", "json"]
    server = local_server.start(command, data / "server-pinned.log")
    try:
        print("after, one CPU: unary, closed loop", flush=True)
        results["after/bench-one-cpu/unary-closed"] = nak_bench(
            args.after, LOADS[1], data / "one-cpu-unary-closed.json", args.seconds, prefix=pin
        )
    finally:
        server.terminate()
        server.wait(timeout=30)
    results["wake_round_trip_us"] = {"same_cpu": wake_round_trip_us(0, 0), "across_cpus": wake_round_trip_us(0, 1)}
    results["floor_us"] = transport_floors(across_cpus_only=False)
    results["steal_percent"] = steal_percent(started, cpu_times())
    (data / "results.json").write_text(json.dumps(results, indent=2) + "\n")


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor()


def render(args: argparse.Namespace) -> None:
    results = json.loads((args.data / "results.json").read_text())
    rows = []
    for load in LOADS:
        for client in ["bench", "python"]:
            name = "nak bench" if client == "bench" else "Python grpcio"
            for server_kind in SERVERS:
                r = results[f"{server_kind.key}/{client}/{load.key}"]
                lat, srv = r["latency_us"], r["server_us"]
                cells = [lat["p50"], lat["p99"], srv["p50"], lat["p50"] - srv["p50"]]
                rows.append((load.label, name, server_kind.label, cells))
    stages = "\n".join(
        "| {} | {} | {:.0f} | {:.0f} | {:.0f} | {:.0f} | {:.0f} | {:.0f} |".format(
            load.label,
            server_kind.label,
            r["latency_us"]["p50"],
            r["generator_us"]["p50"],
            r["server_us"]["p50"],
            r["server_queue_us"]["p50"],
            r["latency_us"]["p50"] - r["generator_us"]["p50"] - r["server_us"]["p50"],
            r["client_cpu_us"],
        )
        for load in LOADS
        for server_kind in SERVERS[1:]
        for r in [results[f"{server_kind.key}/bench/{load.key}"]]
    )
    old = results["after/old-bench/unary-1k"]
    wake = results["wake_round_trip_us"]
    closed, one_cpu = results["after/bench/unary-closed"], results["after/bench-one-cpu/unary-closed"]
    polled = results["polling/bench/unary-closed"]
    floor, floor_polling = results["floor_us"], results["floor_us_polling"]
    open_loop, open_loop_polling = results["after/bench/unary-1k"], results["polling/bench/unary-1k"]
    stream, stream_polling = results["after/bench/stream-1k"], results["polling/bench/stream-1k"]

    def gap(r: dict[str, Any]) -> float:
        return float(r["latency_us"]["p50"] - r["server_us"]["p50"])

    table = "\n".join(
        f"| {label} | {client} | {server} | " + " | ".join(f"{v:.0f}" for v in cells) + " |"
        for label, client, server, cells in rows
    )
    fig, axes = plt.subplots(1, len(LOADS), figsize=(11, 3.6), sharey=True)
    width = 0.8 / len(SERVERS)
    for ax, load in zip(axes, LOADS, strict=True):
        clients = [("bench", "nak bench"), ("python", "grpcio")]
        for i, server_kind in enumerate(SERVERS):
            x = [c + (i - (len(SERVERS) - 1) / 2) * width for c in range(len(clients))]
            runs = [results[f"{server_kind.key}/{client}/{load.key}"] for client, _ in clients]
            fill, edge = server_kind.colours
            ax.bar(x, [r["latency_us"]["p50"] for r in runs], width, label=f"{server_kind.label}, p50", color=fill)
            ax.scatter(x, [r["latency_us"]["p99"] for r in runs], marker="_", s=200, color=edge)
        ax.axhline(250, color="grey", linestyle=":", linewidth=1)
        ax.set_yscale("log")
        ax.set_xticks(range(len(clients)), [name for _, name in clients])
        ax.set_title(load.label, fontsize=10)
    axes[0].set_ylabel("latency, µs (log scale)")
    axes[0].legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    (args.out.parent / "latency").mkdir(exist_ok=True)
    fig.savefig(args.out.parent / "latency" / "latency.png", dpi=120)

    machine = f"{os.cpu_count()} vCPUs of an {cpu_model()}, Linux {platform.release()}"
    args.out.write_text(
        f"""# Serving latency

Generated by `scripts/latency-report --before BIN` (do not edit by hand): the before and after servers
measured in one run, one after the other, on {machine}; release builds; the embedded phantom (9,701
nodes), the Kelvinlet prior, two graspers; load generator and server on the same two cores.
`before`: {args.before_label}. `after`: this checkout. The machine is shared: compare within this
table, not with other runs. During this run the hypervisor gave {results["steal_percent"]:.1f} % of
the CPUs' time to other guests (steal time, /proc/stat).

![p50 and p99 before and after](latency/latency.png)

Bars: p50; dashes: p99; dotted line: 250 µs.

Latency is from each request's due time (open loop) or send time (closed loop) to its answer; server
is the server's own account of each answer (`Timing.total_us`: after the change the whole handler,
before the engine only, so the before column understates the server); client − server is what the
network stack,
the codecs and the client take. `nak bench` is the after build's in every row; the Python client
(scripts/latency_client.py, {results["after/python/unary-1k"]["client"]}) shares no code with it and
sends two graspers of ten nodes each. The third server of each group is the after build started with
`--poll-idle-cpus`: while it runs, idle CPUs poll instead of halting (see the last section). Times in µs.

| load | client | server | p50 | p99 | server p50 | client − server |
|---|---|---|---|---|---|---|
{table}

## Where the time goes (`nak bench`, medians in µs)

The generator's delay from due time to handing the request to the gRPC client, the server's whole
handler (of which waiting for a compute thread: histograms start at 1 µs, so 1 means none), and the
rest: the client's encoding and decoding, HTTP/2 and the loopback network stack in both directions,
and the wake-ups of the idle threads on either side. Encoding a full answer takes 2.8 µs and decoding
a request 0.5 µs (`cargo bench --bench codec`). The last column is not a median but `nak bench`'s own
CPU time per request (`client_cpu_us`: all its threads, user and system, the kernel's work for its
socket included): what the client side of each call costs, on the same two cores as the server.

| load | server | latency | generator | server | server: queue | outside both | client CPU per request |
|---|---|---|---|---|---|---|---|
{stages}

At 1,000 requests/s `nak bench` spent **{open_loop["client_cpu_us"]:.0f} µs** of CPU per unary call
against **{stream["client_cpu_us"]:.0f} µs** per message on a stream: each unary call opens and closes
an HTTP/2 stream of its own (headers both ways, then trailers), in many small steps through tonic,
hyper and h2; on two shared cores that CPU is latency too. Both open-loop figures include the
generator's spin of up to 100 µs before each due time (its timer fires early because waking an idle
CPU is slow, see below); in a closed loop, without it, a unary call cost the client
**{closed["client_cpu_us"]:.0f} µs**.

## The load generator's own delay

The same after server, unary at 1,000 requests/s, loaded by the before and the after `nak bench`:
p50 **{old["latency_us"]["p50"]:.0f} µs** with the before generator (a `nanosleep` thread handing each
request to the runtime), **{open_loop["latency_us"]["p50"]:.0f} µs** with the after one (a timerfd on the
runtime's own thread). The after generator reports its delay from due time to hand-over to the gRPC
client: p50 **{open_loop["generator_us"]["p50"]:.0f} µs**, p99 **{open_loop["generator_us"]["p99"]:.0f} µs**.

## Waking an idle CPU, and not letting CPUs halt

One byte passed back and forth between two processes through pipes (Python, `wake_round_trip_us` in
scripts/latency_report.py) takes **{wake["same_cpu"]:.1f} µs** a round trip when both are on one CPU and
**{wake["across_cpus"]:.1f} µs** when they are on different CPUs: about
**{(wake["across_cpus"] - wake["same_cpu"]) / 2:.0f} µs** for each wake-up of a CPU that had gone idle (this
virtual machine's guest halt-polling is off, so an idle vCPU halts and a wake-up goes through the
hypervisor). A unary call whose client and server wait on different CPUs pays two such wake-ups: the
server's on the request, the client's on the answer. With the after server and `nak bench` both pinned to
CPU 0 (`taskset -c 0`), unary closed loop on one connection: p50 **{one_cpu["latency_us"]["p50"]:.0f} µs**,
client − server **{gap(one_cpu):.0f} µs**, against **{gap(closed):.0f} µs** on two CPUs above; what is
left is the work itself (HTTP/2, the 116 kB answer through loopback TCP, the codecs), done on one CPU;
the last section measures how much of it the loopback exchange alone takes.

`nak serve --poll-idle-cpus` removes the wake-ups instead of avoiding them: for as long as the server
runs it holds a CPU latency QoS request of 0 µs (`/dev/cpu_dma_latency`, root only), under which the
kernel's cpuidle governor keeps idle CPUs in their polling state. The request holds for the whole
machine, so a client on the same machine gains too (`nak bench --poll-idle-cpus` makes the same request
on a load generator's own machine). While that server ran, the cross-CPU round trip took
**{results["wake_round_trip_us_polling"]:.1f} µs**, and unary closed loop on one connection had client −
server **{gap(polled):.0f} µs** on two CPUs. The price: idle CPUs spin at full power instead of sleeping,
so it is opt-in, for machines that serve latency-critical clients.

## The transport's floor: the same bytes without gRPC

How much of client − server is HTTP/2, gRPC and the codecs, and how much the machine's loopback TCP
and its wake-ups would take anyway? Two Python processes exchange the same bytes over loopback TCP, a
{REQUEST_BYTES}-byte request and the answer, one exchange every millisecond as at 1,000 requests/s, and
nothing else (`loopback_floor_us` in scripts/latency_report.py; medians of {FLOOR_ROUNDS:,} exchanges, in µs).
The last row sends the full field over a Unix-domain socket instead, as a client on the server's
machine could (gRPC's `unix:` targets; nak serves TCP only):

| answer | one CPU | two CPUs | two CPUs, idle CPUs polling |
|---|---|---|---|
| a full field, {ANSWER_BYTES:,} bytes | {floor["full_same_cpu"]:.0f} | {floor["full_across_cpus"]:.0f} | \
{floor_polling["full_across_cpus"]:.0f} |
| 1,000 bytes | {floor["small_same_cpu"]:.0f} | {floor["small_across_cpus"]:.0f} | {floor_polling["small_across_cpus"]:.0f} |
| a full field, over a Unix socket | {floor["full_unix_same_cpu"]:.0f} | {floor["full_unix_across_cpus"]:.0f} | \
{floor_polling["full_unix_across_cpus"]:.0f} |

Python adds a few µs a call on each side, so these are upper bounds of the floor. Against them, nak's
client − server at 1,000/s: unary **{gap(open_loop):.0f} µs** (floor
{floor["full_across_cpus"]:.0f}), **{gap(open_loop_polling):.0f} µs** with idle CPUs polling (floor
{floor_polling["full_across_cpus"]:.0f}); stream **{gap(stream):.0f} µs** and
**{gap(stream_polling):.0f} µs**. What HTTP/2, gRPC, the codecs and the hand-offs inside each process add
is at least the difference. The 1,000-byte row separates the exchange from the answer's size: on
two CPUs a 1 kB answer took {floor["small_across_cpus"]:.0f} µs against {floor["full_across_cpus"]:.0f} µs
for a full field, and with idle CPUs polling {floor_polling["small_across_cpus"]:.0f} µs against
{floor_polling["full_across_cpus"]:.0f} µs: where idle CPUs halt, the wake-ups are most of the floor; where
they poll, moving the answer's bytes through loopback TCP is.
"""
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    m = sub.add_parser("measure")
    m.add_argument("--before", type=Path, required=True, help="the nak binary to compare against")
    m.add_argument("--after", type=Path, default=ROOT / "target/release/nak")
    m.add_argument("--seconds", type=int, default=5)
    m.add_argument("--data", type=Path, default=ROOT / "target/latency-report")
    r = sub.add_parser("render")
    r.add_argument("--data", type=Path, default=ROOT / "target/latency-report")
    r.add_argument("--before-label", required=True)
    r.add_argument("--out", type=Path, default=ROOT / "docs/reports/latency.md")
    args = parser.parse_args()
    if args.command == "measure":
        measure(args)
    else:
        render(args)


if __name__ == "__main__":
    main()
