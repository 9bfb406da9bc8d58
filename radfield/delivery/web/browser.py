"""Headless Chromium driven over the DevTools protocol: open a page at an exact viewport, wait for
it to say it is ready, read its pixels, evaluate JavaScript in it. `radfield bench-web` times the
browser renderer with it and the tests compare its frames with `render()`'s.

Chromium is the system's (`chromium`, `chromium-browser` or $RADFIELD_CHROMIUM), run with its
software GL (SwiftShader) unless `gpu`. The protocol is spoken with `websockets` (a dependency of
the server viewer already), so nothing is downloaded.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from radfield.errors import RadfieldError

WAIT = 120.0   # seconds, upper bound of every wait (a busy 2-core machine)


def chromium_path() -> str | None:
    return os.environ.get("RADFIELD_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")


class Page:
    """The one page of a headless Chromium, over its DevTools websocket."""

    def __init__(self, websocket):
        self.ws, self.next_id = websocket, 0

    def call(self, method: str, timeout: float = WAIT, **params) -> dict:
        """One DevTools call; its result (events that arrive meanwhile are dropped)."""
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            reply = json.loads(self.ws.recv(timeout=timeout))
            if reply.get("id") == self.next_id:
                if "error" in reply:
                    raise RadfieldError(f"chromium: {method}: {reply['error'].get('message')}")
                return reply["result"]

    def evaluate(self, expression: str, timeout: float = WAIT):
        """The value of a JavaScript expression in the page (promises awaited)."""
        reply = self.call("Runtime.evaluate", timeout=timeout, expression=expression, returnByValue=True,
                          awaitPromise=True)
        if "exceptionDetails" in reply:
            details = reply["exceptionDetails"]
            raise RadfieldError(f"chromium: {details.get('exception', {}).get('description') or details.get('text')}")
        return reply["result"].get("value")

    def open(self, url: str, width: int, height: int) -> None:
        """Load `url` in a viewport of exactly width × height CSS pixels at device scale 1."""
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)
        self.call("Page.navigate", url="about:blank")   # a new document even where only the URL's hash changes
        self.wait_for("document.URL === 'about:blank'", "a blank page")
        self.call("Page.navigate", url=url)

    def wait_for(self, expression: str, what: str, timeout: float = WAIT):
        """Poll a JavaScript expression until it is truthy; its value."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            value = self.evaluate(expression)
            if value:
                return value
            time.sleep(0.05)
        raise RadfieldError(f"chromium: timed out after {timeout:.0f} s waiting for {what}")

    def wait_ready(self, timeout: float = WAIT) -> None:
        """Wait for the page's `<html data-ready>` (its first frame at the asked view is drawn) or its
        `data-error` (raised, with the page's message)."""
        root = "document.documentElement"   # null while the navigation replaces the document
        state = self.wait_for(f"{root} && ({root}.hasAttribute('data-ready') ? 'ready' : {root}.getAttribute('data-error'))",
                              "the page to draw", timeout)
        if state != "ready":
            raise RadfieldError(f"the page reports: {state}")

    def screenshot(self) -> np.ndarray:
        """The viewport's pixels (H, W, 3) uint8 RGB."""
        import cv2

        png = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


@contextlib.contextmanager
def headless_chromium(gpu: bool = False) -> Iterator[Page]:
    """A headless Chromium (software GL unless `gpu`) and its page; killed on exit."""
    from websockets.sync.client import connect

    binary = chromium_path()
    if binary is None:
        raise RadfieldError("chromium is not installed (apt-get install chromium, or set RADFIELD_CHROMIUM)")
    gl = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader"] if not gpu else ["--enable-gpu", "--ignore-gpu-blocklist"]
    # Chromium's helpers (renderer, GPU, crashpad) outlive a killed parent and go on writing into
    # the profile, so the browser gets its own process group, killed whole, and the profile's removal
    # retries rather than failing a finished run on a file written a moment late.
    with tempfile.TemporaryDirectory(prefix="radfield-chromium-", ignore_cleanup_errors=True) as profile:
        browser = subprocess.Popen([binary, "--headless", "--no-sandbox", "--disable-gpu-sandbox", *gl,
                                    "--no-first-run", "--disable-extensions", f"--user-data-dir={profile}",
                                    "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0",
                                    "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                   start_new_session=True)
        try:
            active = Path(profile) / "DevToolsActivePort"
            end = time.monotonic() + WAIT
            while not (active.is_file() and active.read_text().split("\n")[0]):
                if browser.poll() is not None or time.monotonic() > end:
                    raise RadfieldError(f"chromium ({binary}) did not start")
                time.sleep(0.05)
            port = int(active.read_text().split("\n")[0])
            targets = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=30).read())
            target = next(t for t in targets if t["type"] == "page")
            with connect(target["webSocketDebuggerUrl"], max_size=None, open_timeout=30) as ws:
                yield Page(ws)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(browser.pid, signal.SIGKILL)
            browser.wait(timeout=30)
            _remove_profile(Path(profile))


def _remove_profile(profile: Path, attempts: int = 20) -> None:
    for _ in range(attempts):
        shutil.rmtree(profile, ignore_errors=True)
        if not profile.exists():
            return
        time.sleep(0.1)
