"""Overload and soak runs against a release `nak serve` on loopback (issue: reliability).

overload  measure capacity (closed loop), then offer twice that in an open loop to servers with
          several admission bounds (--max-in-flight) and compute priorities (--compute-niceness), on
          the quick path (the prior computed on the thread that read the request) and on the compute
          pool (--quick-terms 0), server and load generator on separate cores: are admitted requests
          answered within 5 ms at p99, refusals within 1 ms, only OK and RESOURCE_EXHAUSTED returned,
          memory bounded, the server alive afterwards?
burst     1,500 concurrent calls from one Python grpc.aio client: how soon are the refused ones
          refused and the admitted ones answered, against the same burst of GetStatus calls (what the
          client itself takes to send and receive that many)?
soak      ten minutes of four 1 kHz streams plus unary traffic: does the server's memory stay flat
          after warm-up, and the last minute's p99 within 1.5x the first's?
render    docs/reports/reliability.md and its plots from the JSON the two runs wrote

`scripts/reliability` builds the release binary and runs all three. Each run writes
target/reliability/<run>.json; nothing here asserts, the page states what was measured.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import statistics
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import local_server  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
NAK = ROOT / "target" / "release" / "nak"
DATA = ROOT / "target" / "reliability"
DOCS = ROOT / "docs" / "reports"
DEFAULT_NICENESS = 5  # nak serve's --compute-niceness default


class Server:
    """`nak serve` on the embedded phantom, its resident memory sampled in the background."""

    def __init__(self, port: int, every_s: float, *flags: str, cpus: str | None = None) -> None:
        self.log_path = DATA / f"server-{port}.log"
        self.process = local_server.start(
            [*pinned(cpus), str(NAK), "serve", "--listen", f"127.0.0.1:{port}", "--log-format", "json", *flags],
            self.log_path,
        )
        self.target = f"http://127.0.0.1:{port}"
        self.started = time.monotonic()
        self.rss: list[tuple[float, float]] = []  # (seconds since start, MiB)
        self.every_s = every_s
        self.stopping = threading.Event()
        self._sample_once()
        self.sampler = threading.Thread(target=self._sample, daemon=True)
        self.sampler.start()

    def _sample_once(self) -> bool:
        try:
            status = Path(f"/proc/{self.process.pid}/status").read_text()
        except OSError:
            return False
        kib = next((int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS:")), None)
        if kib is None:
            return False
        self.rss.append((time.monotonic() - self.started, kib / 1024))
        return True

    def _sample(self) -> None:
        while not self.stopping.wait(self.every_s) and self._sample_once():
            pass

    def alive(self) -> bool:
        return self.process.poll() is None

    def stop(self) -> int:
        self.stopping.set()
        self.process.terminate()
        return self.process.wait(timeout=30)


def pinned(cpus: str | None) -> list[str]:
    """The command prefix that confines a process to `cpus` (taskset's list syntax), if any."""
    return ["taskset", "--cpu-list", cpus] if cpus else []


def split_cpus() -> tuple[str, str] | None:
    """The server's cores and the load generator's: the first half and the rest, so that the load
    generator does not take the server's cores when both saturate them (None on one core)."""
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        return None
    half = len(cpus) // 2
    return ",".join(map(str, cpus[:half])), ",".join(map(str, cpus[half:]))


def bench(target: str, name: str, *args: str, cpus: str | None = None) -> subprocess.Popen[bytes]:
    """Starts `nak bench`, its JSON report going to DATA/<name>.json."""
    output = str(DATA / f"{name}.json")
    command = [*pinned(cpus), str(NAK), "bench", "--target", target, "--seed", "1", "--output", output, *args]
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def finish(process: subprocess.Popen[bytes], name: str) -> dict[str, Any]:
    if process.wait() != 0:
        raise SystemExit(f"nak bench {name} failed (exit {process.returncode})")
    report: dict[str, Any] = json.loads((DATA / f"{name}.json").read_text())
    return report


def machine() -> str:
    cpu = next(
        (
            line.split(":", 1)[1].strip()
            for line in Path("/proc/cpuinfo").read_text().splitlines()
            if "model name" in line
        ),
        platform.processor(),
    )
    return f"{os.cpu_count()} vCPU {cpu}, {platform.system()} {platform.release()}"


# Where a Kelvinlet request is computed: on the thread that read it (the default for the phantom), or
# handed to the compute pool (every request, with --quick-terms 0).
PATH_FLAGS = {"quick": [], "pool": ["--quick-terms", "0"]}


def capacity_of(path: str, server_cpus: str | None, bench_cpus: str | None) -> dict[str, Any]:
    """What the server answers per second on `path`, closed loop, every worker's request admitted."""
    server = Server(50120, 1.0, "--max-in-flight", "1000", *PATH_FLAGS[path], cpus=server_cpus)
    name = f"capacity-{path}"
    report = finish(
        bench(server.target, name, "--rate", "max", "--concurrency", "8", "--duration", "10s", cpus=bench_cpus), name
    )
    server.stop()
    return report


def answered_rps(report: dict[str, Any]) -> float:
    return float(report["throughput_rps"] - sum(report["errors"].values()) / report["duration_s"])


def overload(duration_s: int, limits: list[int], repeats: int) -> None:
    server_cpus, bench_cpus = split_cpus() or (None, None)
    capacity = {path: capacity_of(path, server_cpus, bench_cpus) for path in PATH_FLAGS}
    offered = {path: 2 * answered_rps(report) for path, report in capacity.items()}
    # Each admission bound on the quick path at the default priority; the middle one with the compute
    # threads level with the runtime's (--compute-niceness 0), to show what the lower priority buys;
    # and the middle one on the pool. Repeats go round all settings in turn, so that a noisy spell on a
    # shared machine does not land on one setting only.
    middle = limits[len(limits) // 2]
    settings = [("quick", limit, DEFAULT_NICENESS) for limit in limits]
    settings += [("quick", middle, 0), ("pool", middle, DEFAULT_NICENESS)]
    runs = []
    for repeat in range(repeats):
        for path, limit, niceness in settings:
            run = overload_once(path, offered[path], duration_s, limit, niceness, server_cpus, bench_cpus)
            runs.append({"repeat": repeat, **run})
            report = run["overload"]
            print(
                f"repeat {repeat + 1}/{repeats}, {path}, max-in-flight {limit}, niceness {niceness}: answered p99 "
                f"{report['answered_us']['p99']:.0f} µs, refused p99 {(report['refused_us'] or {}).get('p99')} µs, "
                f"errors {report['errors']}"
            )
    result = {
        "machine": machine(),
        "server_cpus": server_cpus,
        "bench_cpus": bench_cpus,
        "capacity_rps": {path: answered_rps(report) for path, report in capacity.items()},
        "capacity": capacity,
        "offered_rps": offered,
        "repeats": repeats,
        "runs": runs,
    }
    (DATA / "overload-run.json").write_text(json.dumps(result, indent=2) + "\n")


def overload_once(
    path: str,
    offered: float,
    duration_s: int,
    limit: int,
    niceness: int,
    server_cpus: str | None,
    bench_cpus: str | None,
) -> dict[str, Any]:
    """One fresh server under `offered` requests/s, then a gentle check that it still answers."""
    flags = ["--max-in-flight", str(limit), "--compute-niceness", str(niceness), *PATH_FLAGS[path]]
    server = Server(50121, 0.25, *flags, cpus=server_cpus)
    idle = max(mib for _, mib in server.rss)
    loaded_from = time.monotonic() - server.started
    load = ("--rate", f"{offered:.0f}", "--concurrency", "8", "--duration", f"{duration_s}s", "--warmup", "2s")
    report = finish(bench(server.target, "overload", *load, cpus=bench_cpus), "overload")
    after = finish(bench(server.target, "after", "--rate", "50", "--duration", "2s", cpus=bench_cpus), "after")
    alive = server.alive()
    rss = list(server.rss)
    return {
        "path": path,
        "max_in_flight": limit,
        "compute_niceness": niceness,
        "overload": report,
        "after": after,
        "alive": alive,
        "exit_code": server.stop(),
        "rss_mib": rss,
        "rss_idle_mib": idle,
        "rss_peak_mib": max(mib for t, mib in rss if t >= loaded_from),
    }


async def fire(target: str, calls: int, method: str) -> list[tuple[str, float]]:
    """`calls` concurrent calls of `method` ("predict": the Kelvinlet with two graspers; "status":
    GetStatus, which the server answers without computing) from one grpc.aio client: each call's status
    code and its latency in µs, from just before the call was sent until its answer was handed back."""
    import grpc
    from nak_client import AsyncClient, Grasp

    async with AsyncClient(target) as nak:
        mesh = await nak.mesh()
        grasps = [
            Grasp(nodes=mesh.node_sets["grasp_02"][:6], displacement=(0.0, 0.02, 0.01)),
            Grasp(nodes=mesh.node_sets["grasp_07"][:6], displacement=(0.01, -0.01, 0.0)),
        ]
        await nak.predict(grasps)

        async def one() -> tuple[str, float]:
            start = time.perf_counter()
            try:
                if method == "predict":
                    await nak.predict(grasps)
                else:
                    await nak.status()
                code = "OK"
            except grpc.aio.AioRpcError as refused:
                code = refused.code().name
            return code, (time.perf_counter() - start) * 1e6

        return list(await asyncio.gather(*(one() for _ in range(calls))))


def burst(calls: int, rounds: int) -> None:
    server_cpus, client_cpus = split_cpus() or (None, None)
    server = Server(50123, 0.25, cpus=server_cpus)
    if client_cpus:
        os.sched_setaffinity(0, {int(cpu) for cpu in client_cpus.split(",")})
    grpc_target = server.target.removeprefix("http://")
    bursts = []
    for round_ in range(rounds):
        for method in ("status", "predict"):
            calls_seen = asyncio.run(fire(grpc_target, calls, method))
            bursts.append({"round": round_, "method": method, "calls": calls_seen})
            codes = sorted({code for code, _ in calls_seen})
            print(f"round {round_ + 1}/{rounds}, {method}: {len(calls_seen)} calls, codes {codes}")
    alive = server.alive()
    result = {
        "machine": machine(),
        "server_cpus": server_cpus,
        "client_cpus": client_cpus,
        "calls": calls,
        "bursts": bursts,
        "alive": alive,
        "exit_code": server.stop(),
    }
    (DATA / "burst-run.json").write_text(json.dumps(result) + "\n")


def soak(minutes: int, niceness: int) -> None:
    server = Server(50122, 5.0, "--compute-niceness", str(niceness))
    duration = f"{minutes}m"
    common = ["--duration", duration, "--warmup", "5s", "--interval", "1m"]
    streams = bench(server.target, "soak-streams", "--mode", "stream", "--concurrency", "4", "--rate", "4000", *common)
    unary = bench(server.target, "soak-unary", "--mode", "unary", "--concurrency", "2", "--rate", "200", *common)
    stream_report, unary_report = finish(streams, "soak-streams"), finish(unary, "soak-unary")
    alive = server.alive()
    rss = list(server.rss)
    code = server.stop()
    result = {
        "machine": machine(),
        "minutes": minutes,
        "compute_niceness": niceness,
        "streams": stream_report,
        "unary": unary_report,
        "alive": alive,
        "exit_code": code,
        "rss_mib": rss,
    }
    (DATA / "soak-run.json").write_text(json.dumps(result, indent=2) + "\n")
    print(f"soak done: alive {alive}, exit {code}")


def rss_after(rss: list[list[float]], seconds: float) -> float:
    """The first sample taken at least `seconds` after start."""
    return next(mib for t, mib in rss if t >= seconds)


Setting = tuple[str, int, int]


def group_by_setting(runs: list[dict[str, Any]]) -> dict[Setting, list[dict[str, Any]]]:
    """Overload runs by (path, --max-in-flight, --compute-niceness), in the order they were first run."""
    settings: dict[Setting, list[dict[str, Any]]] = {}
    for run in runs:
        settings.setdefault((run["path"], run["max_in_flight"], run["compute_niceness"]), []).append(run)
    return settings


def other_codes(report: dict[str, Any]) -> int:
    """Errors other than RESOURCE_EXHAUSTED (the admission bound's refusal): there should be none."""
    return sum(n for code, n in report["errors"].items() if code != "RESOURCE_EXHAUSTED")


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else 0.0


def burst_rows(bursts: list[dict[str, Any]]) -> tuple[str, dict[str, list[float]]]:
    """The burst table (one row per kind of outcome, pooled over the rounds) and each kind's latencies."""
    kinds: dict[str, list[float]] = {}
    for b in bursts:
        for code, us in b["calls"]:
            kind = "GetStatus" if b["method"] == "status" else f"Predict {code}"
            kinds.setdefault(kind, []).append(us)
    rows = [
        f"| {kind} | {len(us)} | {percentile(us, 0.5) / 1e3:.1f} | {percentile(us, 0.99) / 1e3:.1f} |"
        f" {max(us) / 1e3:.1f} |"
        for kind, us in sorted(kinds.items())
    ]
    return "\n".join(rows), kinds


def render() -> None:
    load = json.loads((DATA / "overload-run.json").read_text())
    soaked = json.loads((DATA / "soak-run.json").read_text())
    bursted = json.loads((DATA / "burst-run.json").read_text())
    figures = DOCS / "reliability"
    figures.mkdir(parents=True, exist_ok=True)

    warm = 60.0 + 5.0  # the warm-up, then the first minute
    rss = soaked["rss_mib"]
    rss_warm, rss_end = rss_after(rss, warm), rss[-1][1]
    s_int, u_int = soaked["streams"]["intervals"], soaked["unary"]["intervals"]

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 3.6))
    left.plot([t / 60 for t, _ in rss], [m for _, m in rss])
    left.set(xlabel="minutes", ylabel="server RSS (MiB)", title="memory")
    left.set_ylim(bottom=0)
    for name, intervals in (("4 streams × 1 kHz", s_int), ("unary 200/s", u_int)):
        right.plot(
            [i["start_s"] / 60 + 1 for i in intervals],
            [i["latency_us"]["p99"] / 1e3 for i in intervals],
            "o-",
            label=name,
        )
    right.set(xlabel="minute", ylabel="p99 latency (ms)", title="p99 per minute")
    right.set_ylim(bottom=0)
    right.legend()
    fig.tight_layout()
    fig.savefig(figures / "soak.png", dpi=110)

    settings = group_by_setting(load["runs"])
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 3.6))
    for i, ((path, limit, niceness), runs) in enumerate(settings.items()):
        colour = f"C{i}"
        label = f"{path}, max-in-flight {limit}, niceness {niceness}"
        for k, run in enumerate(runs):
            left.plot(
                [t for t, _ in run["rss_mib"]], [m for _, m in run["rss_mib"]], colour, label=None if k else label
            )
            o = run["overload"]
            right.plot(i - 0.1, o["answered_us"]["p99"] / 1e3, "o", color=colour)
            right.plot(i + 0.1, (o["refused_us"] or {"p99": 0})["p99"] / 1e3, "x", color=colour)
    left.set(xlabel="seconds", ylabel="server RSS (MiB)", title="memory at twice the capacity offered")
    left.set_ylim(bottom=0)
    left.legend(fontsize=8)
    right.axhline(5, color="grey", linestyle="--", linewidth=0.8)
    right.axhline(1, color="grey", linestyle=":", linewidth=0.8)
    right.set_xticks(
        range(len(settings)), [f"{path}\n{limit} / {niceness}" for path, limit, niceness in settings], fontsize=8
    )
    right.set(
        xlabel="path, --max-in-flight / --compute-niceness",
        ylabel="p99 (ms)",
        title="p99 per run: answered ○ (target 5 ms), refused × (1 ms)",
    )
    right.set_yscale("log")
    fig.tight_layout()
    fig.savefig(figures / "overload.png", dpi=110)

    def overload_row(setting: Setting, runs: list[dict[str, Any]]) -> str:
        def stat(pick: Any) -> float:
            return float(statistics.median(pick(run["overload"]) for run in runs))

        def p99_spread(key: str) -> str:
            values = [(run["overload"][key] or {"p99": 0})["p99"] for run in runs]
            return f"{statistics.median(values):.0f} ({min(values):.0f}–{max(values):.0f})"

        healthy = all(run["alive"] and run["exit_code"] == 0 and not run["after"]["errors"] for run in runs)
        idle = min(run["rss_idle_mib"] for run in runs)
        peak = max(run["rss_peak_mib"] for run in runs)
        others = sum(other_codes(run["overload"]) for run in runs)
        return (
            f"| {setting[0]} | {setting[1]} | {setting[2]} "
            f"| {stat(lambda o: (o['requests'] - sum(o['errors'].values())) / o['duration_s']):.0f} "
            f"| {stat(lambda o: o['answered_us']['p50']):.0f} | {p99_spread('answered_us')} "
            f"| {stat(lambda o: sum(o['errors'].values()) / o['duration_s']):.0f} "
            f"| {stat(lambda o: (o['refused_us'] or {'p50': 0})['p50']):.0f} | {p99_spread('refused_us')} "
            f"| {others} | {idle:.0f} → {peak:.0f} | {'yes' if healthy else 'NO'} |"
        )

    def verdict(setting: Setting, runs: list[dict[str, Any]]) -> str:
        def median_p99_ms(key: str) -> float:
            return float(statistics.median((run["overload"][key] or {"p99": 0})["p99"] for run in runs)) / 1e3

        answered, refused = median_p99_ms("answered_us"), median_p99_ms("refused_us")
        return (
            f"- {setting[0]} path, `--max-in-flight {setting[1]}`, `--compute-niceness {setting[2]}`: answered p99 "
            f"{answered:.1f} ms ({'meets' if answered <= 5 else 'misses'} 5 ms), refused p99 {refused:.1f} ms "
            f"({'meets' if refused <= 1 else 'misses'} 1 ms)"
        )

    burst_table, kinds = burst_rows(bursted["bursts"])
    fig, axis = plt.subplots(figsize=(7, 3.6))
    for kind, us in sorted(kinds.items()):
        ordered = sorted(us)
        axis.plot([u / 1e3 for u in ordered], [(k + 1) / len(ordered) for k in range(len(ordered))], label=kind)
    axis.set(
        xlabel="latency from the call's send (ms)",
        ylabel="share of calls",
        title=f"{bursted['calls']} concurrent calls from one grpc.aio client",
    )
    axis.set_xscale("log")
    axis.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(figures / "burst.png", dpi=110)

    def row(label: str, intervals: list[dict[str, Any]]) -> str:
        first, last = intervals[0]["latency_us"]["p99"], intervals[-1]["latency_us"]["p99"]
        refusals = sum(i["refused"] for i in intervals)
        return f"| {label} | {first:.0f} | {last:.0f} | {last / first:.2f} | {refusals} |"

    page = f"""# Reliability: overload and soak

Measured by `scripts/reliability` (release build, `nak serve` on the embedded phantom, load from
`nak bench` on the same machine over loopback) on {load["machine"]}. Rerun it on an otherwise idle machine.

## Overload at twice the measured capacity

Both sides of an overload saturate their cores, so here they get their own: the server runs on CPU
{load["server_cpus"]} and `nak bench` on CPU {load["bench_cpus"]} (`taskset`). Sharing the cores instead
measures the load generator's own scheduling delays as much as the server's: a client generating
thousands of requests a second needs a core of its own.

Capacity, closed loop with 8 workers for 10 s against a server that admits every request (Kelvinlet,
two graspers): **{load["capacity_rps"]["quick"]:.0f} answers/s** on the quick path (the prior computed
on the thread that read the request, the default on the phantom) and **{load["capacity_rps"]["pool"]:.0f}**
on the compute pool (`--quick-terms 0`). Then twice that ({load["offered_rps"]["quick"]:.0f} and
{load["offered_rps"]["pool"]:.0f} requests/s) offered in an open loop for
{load["runs"][0]["overload"]["duration_s"]:.0f} s (each unary call sent when due on its own HTTP/2 stream,
latency from the due time) to a fresh server per setting: the path, admission bounds (`--max-in-flight`;
the default is 4 per compute thread, so 4 for a server on one CPU), and the compute threads' priority
below the runtime's (`--compute-niceness`; default 5, 0 = level). A call takes its place when its
headers arrive and holds it until it is answered, on either path. In every run the runtime's threads ask the kernel for its shortest time slice (0.1 ms), so that
one woken by a request preempts a compute thread at once. "Healthy after" means
that it then answered 2 s at 50 requests/s without an error and exited 0 on SIGTERM.

Each setting ran {load["repeats"]} times, the settings taking turns; the table gives medians over
the runs, p99s with their range, memory the lowest idle and the highest peak.

| path | `--max-in-flight` | `--compute-niceness` | answered /s | answered p50 µs | answered p99 µs | refused /s | refused p50 µs | refused p99 µs | codes other than OK and RESOURCE_EXHAUSTED | RSS MiB idle → peak | healthy after |
|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|
{chr(10).join(overload_row(setting, runs) for setting, runs in settings.items())}

![server memory through each run, and each run's p99s](reliability/overload.png)

Targets (issue): admitted p99 ≤ 5 ms, refusals ≤ 1 ms at p99, no status but OK and RESOURCE_EXHAUSTED,
no crash, memory bounded. Medians over the runs against them:

{chr(10).join(verdict(setting, runs) for setting, runs in settings.items())}

## A burst from one Python client

{bursted["calls"]} `Predict` calls (Kelvinlet, two graspers) started at once from one `grpc.aio` client
(`nak_client.AsyncClient`), {len(bursted["bursts"]) // 2} times, against a server with the default
bound; the server on CPU {bursted["server_cpus"]}, the client on CPU {bursted["client_cpus"]}. Each call
is timed from just before it was sent until its answer was handed back to the coroutine, so the client's
own work on {bursted["calls"]} calls counts too: the same burst of `GetStatus` calls, which the server
answers without computing or admitting anything, measures that floor.

| calls | count | p50 ms | p99 ms | max ms |
|---|---:|---:|---:|---:|
{burst_table}

![latency of each call in the bursts, by outcome](reliability/burst.png)

The server was {"alive" if bursted["alive"] else "DOWN"} afterwards and exited with code
{bursted["exit_code"]}.

## Soak: {soaked["minutes"]} minutes of four 1 kHz streams plus unary traffic

Four streams at 1,000 messages/s each and two unary workers at 200 requests/s together, for
{soaked["minutes"]} minutes after a 5 s warm-up; the server's RSS sampled every 5 s. Server and load
generator share both cores here, in one scheduling group.

![server memory and p99 per minute during the soak](reliability/soak.png)

| traffic | first minute p99 µs | last minute p99 µs | last / first | refused |
|---|---:|---:|---:|---:|
{row("4 streams × 1 kHz", s_int)}
{row("unary, 200/s", u_int)}

- RSS after the first minute {rss_warm:.1f} MiB, at the end {rss_end:.1f} MiB: growth
  {100 * (rss_end - rss_warm) / rss_warm:+.1f} %.
- The server was {"alive" if soaked["alive"] else "DOWN"} at the end and exited with code {soaked["exit_code"]}.

Targets (issue): RSS growth < 5 % after warm-up, last minute's p99 within 1.5× of the first's.
"""
    (DOCS / "reliability.md").write_text(page)
    print(f"wrote {DOCS / 'reliability.md'} and its plots")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    load = sub.add_parser("overload")
    load.add_argument("--seconds", type=int, default=20)
    load.add_argument("--limits", type=int, nargs="+", default=[2, 4, 8], help="--max-in-flight values")
    load.add_argument("--repeats", type=int, default=3, help="runs of each setting")
    soak_parser = sub.add_parser("soak")
    soak_parser.add_argument("--minutes", type=int, default=10)
    soak_parser.add_argument("--niceness", type=int, default=DEFAULT_NICENESS, help="--compute-niceness")
    burst_parser = sub.add_parser("burst")
    burst_parser.add_argument("--calls", type=int, default=1500)
    burst_parser.add_argument("--rounds", type=int, default=3)
    sub.add_parser("render")
    args = parser.parse_args()
    DATA.mkdir(parents=True, exist_ok=True)
    if args.command == "overload":
        overload(args.seconds, args.limits, args.repeats)
    elif args.command == "soak":
        soak(args.minutes, args.niceness)
    elif args.command == "burst":
        burst(args.calls, args.rounds)
    else:
        render()


if __name__ == "__main__":
    main()
