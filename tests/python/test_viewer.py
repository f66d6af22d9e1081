"""`nak serve --ui`: the viewer page in a real (headless) Chromium against a running server.

A drag on the organ must deform it on screen (pixels change where the organ is) and fill the latency
readout; the rates of answers and of frames showing a new deformation during a drag are measured and printed (a figure, not a pass mark: speed is
measured by commands, not asserted by tests). NAK_VIEWER_SCREENSHOT=PATH keeps the screenshot after
the drags (the picture in docs/viewer.md: scripts/viewer-screenshot)."""

from __future__ import annotations

import io
import json
import os
import shlex
import statistics
import struct
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from browser import Browser
from PIL import Image

from conftest import start_server_ports

DRAG_SECONDS = 2.0
MOVE_INTERVAL_S = 1 / 120  # a gaming mouse's report rate; an office mouse sends half as many


@pytest.fixture(scope="module")
def viewer(nak_binary: Path) -> Iterator[str]:
    # NAK_VIEWER_SERVE_ARGS: more `nak serve` arguments (another mesh, say: scripts/viewer-screenshot).
    extra = shlex.split(os.environ.get("NAK_VIEWER_SERVE_ARGS", ""))
    with start_server_ports(nak_binary, ["--ui", "127.0.0.1:0", *extra], ["viewer listening"]) as addresses:
        yield f"http://{addresses['viewer listening']}"


def pixels(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def organ_point(browser: Browser, near: tuple[float, float]) -> tuple[float, float]:
    """A pixel over the organ, searched outwards from `near`."""
    for radius in range(0, 200, 10):
        for dx, dy in ((0, 0), (radius, 0), (-radius, 0), (0, radius), (0, -radius)):
            x, y = near[0] + dx, near[1] + dy
            if browser.evaluate(f"nakViewer.hits({x}, {y})"):
                return x, y
    raise AssertionError(f"no organ near {near}")


def drag(browser: Browser, start: tuple[float, float], by: tuple[float, float], shift: bool = False) -> None:
    """Press at `start`, move by `by` in DRAG_SECONDS at the mouse's report rate, release."""
    browser.mouse("mousePressed", *start, shift=shift)
    steps = int(DRAG_SECONDS / MOVE_INTERVAL_S)
    began = time.monotonic()
    for i in range(1, steps + 1):
        time.sleep(max(0.0, began + i * MOVE_INTERVAL_S - time.monotonic()))
        f = i / steps
        browser.mouse("mouseMoved", start[0] + f * by[0], start[1] + f * by[1], shift=shift, wait=False)
    browser.mouse("mouseReleased", start[0] + by[0], start[1] + by[1], shift=shift)
    browser.wait_for("!nakViewer.busy")


def test_dragging_the_organ_deforms_it_on_screen(viewer: str) -> None:
    with Browser(1200, 800) as browser:
        browser.navigate(viewer + "/")
        browser.wait_for("window.nakViewer && (nakViewer.ready || nakViewer.error)")
        assert browser.evaluate("nakViewer.error") is None
        browser.wait_for("nakViewer.framesDrawn > 0")
        before = pixels(browser.screenshot())

        drag(browser, organ_point(browser, (600, 400)), (150, -90))
        drag(browser, organ_point(browser, (450, 450)), (-80, 60), shift=True)
        # Measured: the first grasper taken again by its dot and moved on, both graspers holding.
        handle = browser.evaluate("nakViewer.handle(0)")
        since = browser.evaluate("performance.now()")
        drag(browser, (handle[0], handle[1]), (-60, -40))
        answers = browser.evaluate(f"nakViewer.answerRate({since})")
        frames = browser.evaluate(f"nakViewer.deformationFrameRate({since})")
        round_trips = browser.evaluate(f"nakViewer.roundTripsMs({since})")
        moved = browser.evaluate("nakViewer.handle(0)")
        assert abs(moved[0] - (handle[0] - 60)) < 3 and abs(moved[1] - (handle[1] - 40)) < 3, (handle, moved)
        render_scale = browser.evaluate("nakViewer.renderScale")
        time.sleep(0.2)  # the next animation frame draws the last answer
        after_png = browser.screenshot()
        after = pixels(after_png)

        assert browser.evaluate("nakViewer.error") is None
        assert browser.evaluate("nakViewer.graspers") == 2
        # The readout shows the server's stages and the round trip.
        for element in ("rtt", "server-total", "server-resolve", "server-prior", "server-network"):
            browser.wait_for(f"document.getElementById('{element}').textContent.endsWith('µs')", timeout=5)
        assert int(browser.evaluate("document.getElementById('held').textContent")) > 0

    # Where the organ is (not the page's background), the picture changed: it moved and its colours
    # now show displacement. The panels are left out: their text changes anyway.
    background = before[5, 600]
    organ = np.abs(before - background).sum(axis=2) > 30
    organ[:, :300] = organ[:, -90:] = False
    changed = np.abs(after - before).sum(axis=2) > 40
    share = changed[organ].mean()
    assert organ.sum() > 50_000, "the organ should fill a good part of the view"
    assert share > 0.2, f"only {share:.1%} of the organ's pixels changed"

    report = {
        "deformation_frames_per_s": round(frames, 1),
        "answers_per_s": round(answers, 1),
        "round_trip_ms_p50": round(statistics.median(round_trips), 2),
        "round_trip_ms_max": round(max(round_trips), 2),
        "answers": len(round_trips),
        "render_scale": round(render_scale, 2),
        "organ_pixels_changed": round(float(share), 3),
    }
    print("viewer drag:", json.dumps(report))
    assert frames > 0
    if path := os.environ.get("NAK_VIEWER_SCREENSHOT"):
        Path(path).write_bytes(after_png)


def grpc_web_call(viewer: str, method: str, message: bytes) -> tuple[int, dict[str, str], bytes]:
    """A raw gRPC-Web unary call, as the page makes it: HTTP status, headers and body."""
    request = urllib.request.Request(
        f"{viewer}/nak.v1.Deformation/{method}",
        data=b"\0" + struct.pack(">I", len(message)) + message,
        headers={"content-type": "application/grpc-web+proto", "x-grpc-web": "1"},
    )
    with urllib.request.urlopen(request, timeout=30) as response:
        return response.status, dict(response.headers), response.read()


def test_the_viewer_port_refuses_bad_requests_with_a_grpc_status(viewer: str) -> None:
    # Grasp of node 99999 (the phantom has 9,701): field 2 (Grasp) holding field 1 (nodes) = 99999.
    grasp = b"\x0a\x03" + bytes([0x9F, 0x8D, 0x06])
    status, headers, _ = grpc_web_call(viewer, "Predict", b"\x12" + bytes([len(grasp)]) + grasp)
    assert status == 200
    assert headers["grpc-status"] == "3", headers
    assert "99999" in urllib.parse.unquote(headers["grpc-message"])
    # The page and a good call still work.
    status, _, body = grpc_web_call(viewer, "ListModels", b"")
    assert status == 200 and b"kelvinlet" in body
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(f"{viewer}/nak.v1.Deformation/Predict", timeout=10)
    assert refused.value.code in (400, 405)
