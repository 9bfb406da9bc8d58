"""`radfield view`: the viser viewer in a real browser (headless Chromium, software WebGL), and the
camera conversion it relies on."""

from __future__ import annotations

import base64
import json
import math
import os
import shutil
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from radfield.core.geometry.cameras import Camera, look_at
from radfield.delivery.io import save_model
from radfield.core.kinds import Gaussians, random_gaussians, rotmat_to_quat
from radfield.core.render.rasterize import render
from radfield.core.render.sh import rgb_to_sh_dc
from radfield.delivery.viewer import tet_edges, viser_camera

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
WAIT = 90.0   # seconds, upper bound of every wait (the machine may be busy)


def test_viser_camera_is_the_radfield_camera(monkeypatch):
    """viser reports OpenCV-convention cameras (wxyz, position, vertical fov): the same pixels as
    the radfield camera they came from."""
    monkeypatch.setenv("RADFIELD_KERNELS", "torch")   # a camera check: no need to wait for the C++ build
    c2w = look_at((0.5, -2.5, 1.0), (0, 0, 0))
    fy = 30.0
    ours = Camera(fy, fy, 24.0, 16.0, 48, 32, c2w)
    wxyz = rotmat_to_quat(c2w[:3, :3][None])[0].numpy()
    theirs = viser_camera(wxyz, c2w[:3, 3].numpy(), fov=2 * math.atan(16 / fy), aspect=1.5, height=32)
    assert (theirs.width, theirs.height) == (48, 32)
    assert torch.allclose(theirs.c2w, c2w, atol=1e-12)
    assert math.isclose(theirs.fy, fy) and math.isclose(theirs.fx, fy)
    g = random_gaussians(30, seed=1, extent=0.5)
    assert torch.allclose(render(g, ours).color, render(g, theirs).color, atol=1e-6)


def test_tet_edges():
    edges = tet_edges(np.array([[0, 1, 2, 3], [1, 2, 3, 4]]))
    assert len(edges) == 9 and {tuple(e) for e in edges} >= {(0, 1), (3, 4), (1, 2)}


def _wait(condition, what: str, timeout: float = WAIT):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = condition()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


class _Lines:
    """Collects a process's output lines in a thread (so a full pipe never blocks it)."""

    def __init__(self, stream):
        self.lines: list[str] = []
        start = time.monotonic()
        threading.Thread(target=lambda: [self.lines.append(f"{time.monotonic() - start:6.1f} s  {line}") for line in stream],
                         daemon=True).start()

    def find(self, text: str) -> str | None:
        return next((line for line in self.lines if text in line), None)


def _screenshot(devtools_port: int, path: Path) -> None:
    """Page.captureScreenshot over the DevTools protocol of the page target."""
    from websockets.sync.client import connect

    targets = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{devtools_port}/json/list", timeout=10).read())
    page = next(t for t in targets if t["type"] == "page")
    with connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=10) as ws:
        ws.send(json.dumps({"id": 1, "method": "Page.captureScreenshot", "params": {"format": "png"}}))
        reply = json.loads(ws.recv(timeout=30))
    path.write_bytes(base64.b64decode(reply["result"]["data"]))


@pytest.fixture
def colourful_model(tmp_path) -> Path:
    """Opaque red, green and blue Gaussians filling the middle of the default view."""
    g = random_gaussians(150, extent=0.6, scale=0.15, seed=2)
    rgb = torch.tensor([[1.0, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.2, 1.0]]).repeat(50, 1)
    g = Gaussians(means=g.means, log_scales=g.log_scales, quats=g.quats, sh=rgb_to_sh_dc(rgb)[:, None, :],
                  opacities=torch.full((150,), 3.0))
    save_model(tmp_path / "model.safetensors", g)
    return tmp_path / "model.safetensors"


def test_viewer_shows_the_model_in_headless_chromium(colourful_model, tmp_path):
    if CHROMIUM is None:
        if os.environ.get("CI") == "true":
            pytest.fail("chromium is missing (apt-get install -y chromium): the viewer test cannot run")
        pytest.skip("chromium is not installed (apt-get install -y chromium)")
    # the torch kernels: no wait for the C++ extension, and 150 Gaussians render fast either way
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", "RADFIELD_KERNELS": "torch"}
    server = subprocess.Popen([sys.executable, "-m", "radfield", "view", str(colourful_model), "--host", "127.0.0.1",
                               "--port", "0", "--resolution", "256"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    browser = None
    try:
        log = _Lines(server.stderr)
        _wait(lambda: log.find("viewer: http://") or server.poll() is not None, "the viewer to start")
        assert server.poll() is None, "".join(log.lines)
        port = int(log.find("viewer: http://").split("http://127.0.0.1:")[1].split()[0])
        profile = tmp_path / "chromium-profile"
        browser = subprocess.Popen([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu-sandbox",
                                    "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                                    "--no-first-run", "--disable-extensions", f"--user-data-dir={profile}",
                                    "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0",
                                    "--window-size=640,480", f"http://127.0.0.1:{port}/"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        active = profile / "DevToolsActivePort"
        devtools_port = int(_wait(lambda: active.is_file() and active.read_text().split("\n")[0], "chromium's DevTools"))
        _wait(lambda: log.find("connected"), "the browser to connect to viser")
        # the camera settles (the browser reports its size and pose a few times at start)
        last_frame = lambda: ([line for line in log.lines if "viewer: frame" in line] or [""])[-1]
        _wait(lambda: "(full)" in last_frame(), "a full-resolution frame rendered by the server")
        time.sleep(3.0)   # the browser decodes the frame and fades it in as the scene background
        shot = tmp_path / "viewer.png"
        _screenshot(devtools_port, shot)
    finally:
        for proc in (browser, server):
            if proc is not None:
                proc.kill()
                proc.wait(timeout=30)
    if os.environ.get("RADFIELD_KEEP_SCREENSHOT"):
        shutil.copy(shot, os.environ["RADFIELD_KEEP_SCREENSHOT"])
    image = cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB).astype(np.float64) / 255
    height, width = image.shape[:2]
    assert width == 640 and height > 200
    # the middle of the page (away from the GUI panels) shows the model: many strongly coloured
    # pixels of each of its three colours on the white background
    middle = image[height // 4 : 3 * height // 4, width // 4 : 3 * width // 4]
    saturated = middle.max(-1) - middle.min(-1) > 0.4
    assert saturated.mean() > 0.1, f"only {saturated.mean():.1%} coloured pixels: the model is not shown"
    for channel in range(3):
        dominant = saturated & (middle.argmax(-1) == channel)
        assert dominant.mean() > 0.01, f"colour {channel} of the model is missing"
    assert middle.std() > 0.1


def test_sigterm_stops_the_viewer_with_one_line(colourful_model):
    """A real `radfield view` process and a real SIGTERM: the server is stopped, one line, exit 0
    (it used to die without closing the server; with pycolmap imported, whose glog failure handler
    catches SIGTERM, it printed a 32-line stack dump: pycolmap is imported first when present)."""
    import importlib.util
    import signal

    preload = "import pycolmap; " if importlib.util.find_spec("pycolmap") is not None else ""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", "RADFIELD_KERNELS": "torch"}
    server = subprocess.Popen([sys.executable, "-c", f"{preload}from radfield.cli.main import main; main()", "view",
                               str(colourful_model), "--host", "127.0.0.1", "--port", "0"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    try:
        log = _Lines(server.stderr)
        _wait(lambda: log.find("viewer: http://") or server.poll() is not None, "the viewer to start")
        assert server.poll() is None, "".join(log.lines)
        server.send_signal(signal.SIGTERM)
        code = server.wait(timeout=WAIT)
    finally:
        if server.poll() is None:
            server.kill()
            server.wait(timeout=30)
    time.sleep(0.2)   # the reader thread drains the pipe
    after = log.lines[log.lines.index(log.find("viewer: http://")) + 1:]
    assert code == 0, "".join(log.lines)
    assert len(after) == 1 and after[0].rstrip().endswith("radfield: viewer stopped (SIGTERM)"), "".join(log.lines)
