"""Headless Chromium driven over the DevTools protocol: real pointer input, screenshots, page scripts.

The browser is Debian's `chromium-headless-shell` (scripts/setup-chromium installs it), with WebGL on
SwiftShader, its software rasterizer, since the test machines have no GPU."""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import signal
import subprocess
import tempfile
from contextlib import ExitStack
import time
import urllib.request
from pathlib import Path
from types import TracebackType
from typing import Any

from websockets.sync.client import ClientConnection, connect

CANDIDATES = ("chromium-headless-shell", "chromium")


def chromium_path() -> Path:
    """The browser: $NAK_CHROMIUM, else the first of CANDIDATES on PATH."""
    named = os.environ.get("NAK_CHROMIUM")
    found = named or next((p for p in map(shutil.which, CANDIDATES) if p), None)
    if not found:
        raise FileNotFoundError(
            "no headless Chromium: install Debian's chromium-headless-shell (scripts/setup-chromium) or set NAK_CHROMIUM"
        )
    return Path(found)


class DevToolsError(RuntimeError):
    pass


class Browser:
    """One Chromium with one page, `width` × `height` CSS pixels; use as a context manager."""

    def __init__(self, width: int = 1200, height: int = 800) -> None:
        self.width, self.height = width, height
        self._profile = tempfile.TemporaryDirectory(prefix="nak-chromium-")
        self._process = subprocess.Popen(
            [
                str(chromium_path()),
                "--headless",
                "--no-sandbox",
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                "--remote-debugging-port=0",
                f"--user-data-dir={self._profile.name}",
                f"--window-size={width},{height}",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            # Chromium forks a GPU process and renderers that outlive their parent: its own
            # process group lets __exit__ stop them all.
            start_new_session=True,
        )
        self._ids = itertools.count(1)
        self._resources = ExitStack()
        try:
            self._socket: ClientConnection = self._resources.enter_context(
                connect(self._page_socket(), max_size=None, open_timeout=30)
            )
            self.call(
                "Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False
            )
        except BaseException:
            self._stop()
            raise

    def _page_socket(self) -> str:
        """The page's DevTools WebSocket, once Chromium has written its port."""
        port_file = Path(self._profile.name) / "DevToolsActivePort"
        deadline = time.monotonic() + 30
        while not port_file.exists() or not port_file.read_text().strip():
            if self._process.poll() is not None or time.monotonic() > deadline:
                raise DevToolsError(f"Chromium did not start (exit status {self._process.poll()})")
            time.sleep(0.05)
        port = port_file.read_text().split()[0]
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as response:
            targets = json.load(response)
        return str(next(t["webSocketDebuggerUrl"] for t in targets if t["type"] == "page"))

    def __enter__(self) -> Browser:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, error: BaseException | None, trace: TracebackType | None
    ) -> None:
        self._stop()

    def _stop(self) -> None:
        """Closes the connection and stops every process of the browser's group before its profile
        directory goes (a renderer still writing there would make the removal fail)."""
        self._resources.close()
        group = self._process.pid
        os.killpg(group, signal.SIGTERM)
        self._process.wait(timeout=10)
        deadline = time.monotonic() + 10
        while True:
            try:
                os.killpg(group, signal.SIGKILL if time.monotonic() > deadline else 0)
            except ProcessLookupError:
                break
            time.sleep(0.05)
        self._profile.cleanup()

    def send(self, method: str, **params: Any) -> int:
        """Sends one DevTools command without waiting for it; returns its id."""
        ident = next(self._ids)
        self._socket.send(json.dumps({"id": ident, "method": method, "params": params}))
        return ident

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        """One DevTools command; its result (events, and answers to commands sent without waiting,
        that arrive meanwhile are dropped)."""
        ident = self.send(method, **params)
        while True:
            message = json.loads(self._socket.recv(timeout=60))
            if message.get("id") != ident:
                continue
            if "error" in message:
                raise DevToolsError(f"{method}: {message['error']}")
            result: dict[str, Any] = message["result"]
            return result

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (promises awaited)."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in result:
            raise DevToolsError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def wait_for(self, expression: str, timeout: float = 60) -> Any:
        """Polls `expression` until it is truthy; returns its value."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            value = self.evaluate(expression)
            if value:
                return value
            time.sleep(0.05)
        raise TimeoutError(f"{expression} still false after {timeout} s")

    def navigate(self, url: str) -> None:
        self.call("Page.enable")
        self.call("Page.navigate", url=url)

    def screenshot(self) -> bytes:
        """The viewport as PNG."""
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def mouse(self, kind: str, x: float, y: float, shift: bool = False, wait: bool = True) -> None:
        """A left-button mouse event: kind is mousePressed, mouseMoved or mouseReleased. With `wait`
        false it is sent like a real mouse's report, without waiting for the page to handle it (the
        browser coalesces moves that arrive within one frame)."""
        (self.call if wait else self.send)(
            "Input.dispatchMouseEvent",
            type=kind,
            x=x,
            y=y,
            button="left",
            buttons=0 if kind == "mouseReleased" else 1,
            clickCount=1,
            modifiers=8 if shift else 0,
        )
