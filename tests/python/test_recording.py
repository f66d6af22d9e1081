"""Recordings made by `nak serve --record`, read back with the independent PyPI `mcap` readers."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import client
import grpc
import numpy as np
import pytest
from conftest import start_server
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader
from mcap_protobuf.decoder import DecoderFactory


def grasps(pb: object, stub: object, count: int) -> list[object]:
    mesh = stub.GetMesh(pb.GetMeshRequest())  # type: ignore[attr-defined]
    nodes = next(s for s in mesh.node_sets if s.name == "grasp_05").nodes
    return [
        pb.PredictRequest(  # type: ignore[attr-defined]
            sequence=i,
            grasps=[pb.Grasp(nodes=list(nodes)[:8], displacement=pb.Vec3(y=0.001 * (i + 1)))],  # type: ignore[attr-defined]
        )
        for i in range(count)
    ]


def test_unary_calls_and_a_stream_are_recorded_in_order(nak_binary: Path, tmp_path: Path) -> None:
    pb, rpc = client.load_stubs()
    with start_server(nak_binary, ["--record", str(tmp_path), "--record-payload", "surface"]) as address:
        with grpc.insecure_channel(address) as channel:
            stub = rpc.DeformationStub(channel)
            requests = grasps(pb, stub, 12)
            for r in requests[:5]:
                stub.Predict(r)
            bad = pb.PredictRequest(sequence=99, grasps=[pb.Grasp(nodes=[10**9], displacement=pb.Vec3(y=0.01))])
            with pytest.raises(grpc.RpcError):
                stub.Predict(bad)
            answers = list(stub.PredictStream(iter(requests[5:])))
            assert [a.sequence for a in answers] == list(range(5, 12))
            status = stub.GetStatus(pb.GetStatusRequest())
            assert status.recorder.enabled and status.recorder.dropped == 0
    # start_server stopped it with SIGTERM: the file is finished, with summary and index.
    (recording,) = tmp_path.glob("*.mcap")
    with open(recording, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        assert metadata["nak.server"]["mesh_name"] == "phantom-liver"
        assert len(metadata["nak.server"]["mesh_hash"]) == 64
        assert "kelvinlet" in json.loads(metadata["nak.server"]["models"])
        by_topic: dict[str, list[tuple[int, object]]] = {}
        for _, channel_, message, decoded in reader.iter_decoded_messages():
            by_topic.setdefault(channel_.topic, []).append((message.log_time, decoded))
    requests_seen = by_topic["/nak/requests"]
    assert [r.sequence for _, r in requests_seen] == [0, 1, 2, 3, 4, 99, *range(5, 12)]  # type: ignore[attr-defined]
    log_times = [t for t, _ in requests_seen]
    assert log_times == sorted(log_times)
    responses = [r for _, r in by_topic["/nak/responses"]]
    assert len(responses) == 12  # the refused request has timing but no response
    timing = [t for _, t in by_topic["/nak/timing"]]
    assert len(timing) == 13 and [t.status_code for t in timing].count(3) == 1  # type: ignore[attr-defined]
    first = responses[0]
    u = np.frombuffer(first.displacements, dtype="<f4").reshape(-1, 3)  # type: ignore[attr-defined]
    assert len(first.node_ids) == u.shape[0] == first.node_count > 1000  # type: ignore[attr-defined]
    # The Kelvinlet's force estimate for the one grasp is recorded with the answer.
    (force,) = first.grasp_forces  # type: ignore[attr-defined]
    assert force.y > 0.0  # lifting the region pulls it up
    assert by_topic["/nak/surface"], "no point cloud for Foxglove"
    cloud = by_topic["/nak/surface"][0][1]
    assert cloud.point_stride == 16 and [f.name for f in cloud.fields] == ["x", "y", "z", "displacement_mm"]  # type: ignore[attr-defined]


def test_a_hard_kill_keeps_everything_up_to_the_last_chunk(nak_binary: Path, tmp_path: Path) -> None:
    pb, rpc = client.load_stubs()
    proc = subprocess.Popen(
        [str(nak_binary), "serve", "--listen", "127.0.0.1:0", "--log-format", "json", "--record", str(tmp_path)],
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stderr is not None
    address = next(json.loads(line)["fields"]["address"] for line in proc.stderr if '"listening"' in line)
    sent = 0
    with grpc.insecure_channel(address) as channel:
        stub = rpc.DeformationStub(channel)
        requests = grasps(pb, stub, 40)
        deadline = time.monotonic() + 2.5  # the writer finishes a chunk every second
        while time.monotonic() < deadline:
            stub.Predict(requests[sent % 40])
            sent += 1
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    (recording,) = tmp_path.glob("*.mcap")
    recovered = 0
    topics: dict[int, str] = {}
    with open(recording, "rb") as f:
        try:
            for record in StreamReader(f, skip_magic=False).records:
                if isinstance(record, Channel):
                    topics[record.id] = record.topic
                elif isinstance(record, McapMessage) and topics.get(record.channel_id) == "/nak/requests":
                    recovered += 1
        except McapError:  # the file ends in the chunk being written: everything before it was read
            pass
    assert 0 < recovered <= sent
    # nak replay reads the same file and re-sends what it recovered.
    with start_server(nak_binary, []) as address:
        out = subprocess.run(
            [str(nak_binary), "replay", str(recording), "--target", f"http://{address}", "--pace", "max", "--compare"],
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert out.returncode == 0, out.stderr
    assert f"replayed    {recovered} exchanges" in out.stdout, out.stdout
    assert "mismatched  0 status" in out.stdout
    assert "largest 0.000e0 m" in out.stdout, out.stdout


def test_files_rotate_by_size_and_each_is_complete(nak_binary: Path, tmp_path: Path) -> None:
    pb, rpc = client.load_stubs()
    args = ["--record", str(tmp_path), "--record-payload", "full", "--record-rotate-mb", "1"]
    sent = 0
    with start_server(nak_binary, args) as address:
        with grpc.insecure_channel(address) as channel:
            stub = rpc.DeformationStub(channel)
            requests = grasps(pb, stub, 20)
            # Full fields are ~116 kB: a few per second pass 1 MiB; rotation is checked every second.
            deadline = time.monotonic() + 3.5
            while time.monotonic() < deadline:
                stub.Predict(requests[sent % 20])
                sent += 1
                time.sleep(0.02)
    files = sorted(tmp_path.glob("*.mcap"))
    assert len(files) >= 2, files
    recorded = 0
    for path in files:
        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()  # every file, rotated or last, is finished
            assert summary is not None and summary.statistics is not None
            assert "nak.server" in {m.name for m in reader.iter_metadata()}
            recorded += sum(1 for _, c, _ in reader.iter_messages() if c.topic == "/nak/requests")
    assert recorded == sent
