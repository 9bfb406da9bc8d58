"""`radfield view --server`: the viser viewer in a real browser (headless Chromium, software WebGL), and the
camera conversion it relies on."""

from __future__ import annotations

import base64
import contextlib
import json
import math
import os
import re
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
from radfield.model_file import save_model
from radfield.core.kinds import DynamicGaussians, Gaussians, RelightGaussians, random_gaussians, rotmat_to_quat
from radfield.core.kinds.dynamic import TEMPORAL_TERMS
from radfield.core.kinds.relight import DEFAULT_COLOR_HIDDEN, init_network
from radfield.core.render.rasterize import render
from radfield.core.splat.sh import rgb_to_sh_dc
from radfield.conditions import Asked
from radfield.conditions.light import light_at
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


def _devtools(devtools_port: int, method: str, **params) -> dict:
    """One DevTools-protocol call on the page target; its result."""
    from websockets.sync.client import connect

    targets = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{devtools_port}/json/list", timeout=10).read())
    page = next(t for t in targets if t["type"] == "page")
    with connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=10) as ws:
        ws.send(json.dumps({"id": 1, "method": method, "params": params}))
        while (reply := json.loads(ws.recv(timeout=30))).get("id") != 1:
            pass   # an event, not the reply
    return reply["result"]


def _screenshot(devtools_port: int, path: Path) -> None:
    """Page.captureScreenshot over the DevTools protocol of the page target."""
    path.write_bytes(base64.b64decode(_devtools(devtools_port, "Page.captureScreenshot", format="png")["data"]))


def _in_page(devtools_port: int, script: str):
    """The value of a JavaScript expression evaluated in the page."""
    reply = _devtools(devtools_port, "Runtime.evaluate", expression=script, returnByValue=True)
    assert "exceptionDetails" not in reply, reply
    return reply["result"].get("value")


def _middle_of_page(devtools_port: int, path: Path) -> np.ndarray:
    """The middle of a screenshot left of the GUI panel (its blue slider thumbs would count as the
    model's colour; the panel starts at 48% of the width), RGB in [0, 1], once the last frame has
    been faded in."""
    time.sleep(3.0)   # the browser decodes the frame and fades it in as the scene background
    _screenshot(devtools_port, path)
    image = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB).astype(np.float64) / 255
    height, width = image.shape[:2]
    return image[height // 4 : 9 * height // 10, width // 4 : 45 * width // 100]


def _dominant(image: np.ndarray, channel: int) -> float:
    """The share of strongly coloured pixels whose strongest channel is `channel`."""
    saturated = image.max(-1) - image.min(-1) > 0.4
    return float((saturated & (image.argmax(-1) == channel)).mean())


def _frames(log: "_Lines", since: int = 0) -> list[str]:
    """The viewer's frame log lines (from line `since` on)."""
    return [line for line in log.lines[since:] if "viewer: frame" in line]


def _need_chromium() -> None:
    if CHROMIUM is None:
        if os.environ.get("CI") == "true":
            pytest.fail("chromium is missing (apt-get install -y chromium): the viewer test cannot run")
        pytest.skip("chromium is not installed (apt-get install -y chromium)")


@contextlib.contextmanager
def _viewer_in_chromium(model: Path, tmp_path: Path, *options: str):
    """`radfield view MODEL --server --resolution 256 OPTIONS` and headless Chromium (software WebGL) on its
    page: yields (the viewer's log, Chromium's DevTools port) once the browser has connected; both
    processes are killed on exit."""
    _need_chromium()
    # the torch kernels: no wait for the C++ extension, and 150 Gaussians render fast either way
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", "RADFIELD_KERNELS": "torch"}
    server = subprocess.Popen([sys.executable, "-m", "radfield", "view", str(model), "--server", "--host", "127.0.0.1",
                               "--port", "0", "--resolution", "256", *options],
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
        yield log, devtools_port
    finally:
        for proc in (browser, server):
            if proc is not None:
                proc.kill()
                proc.wait(timeout=30)


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
    shot = tmp_path / "viewer.png"
    with _viewer_in_chromium(colourful_model, tmp_path) as (log, devtools_port):
        # the camera settles (the browser reports its size and pose a few times at start)
        last_frame = lambda: ([line for line in log.lines if "viewer: frame" in line] or [""])[-1]
        _wait(lambda: "(full)" in last_frame(), "a full-resolution frame rendered by the server")
        time.sleep(3.0)   # the browser decodes the frame and fades it in as the scene background
        _screenshot(devtools_port, shot)
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


RED, BLUE = (1.0, 0.1, 0.1), (0.1, 0.2, 1.0)


@pytest.fixture
def red_to_blue(tmp_path) -> Path:
    """Opaque dynamic Gaussians (core/kinds/dynamic.py) that are red at time 0 and turn blue by time
    1: S(ξ) = S0 + a_1 ξ (eq. 10), the other temporal terms 0."""
    g = random_gaussians(150, extent=0.6, scale=0.15, seed=2)
    red, blue = rgb_to_sh_dc(torch.tensor([RED])), rgb_to_sh_dc(torch.tensor([BLUE]))
    sh_t = torch.zeros(150, TEMPORAL_TERMS, 3)
    sh_t[:, 0] = blue - red
    save_model(tmp_path / "dynamic.safetensors",
               DynamicGaussians(means=g.means, log_scales=g.log_scales, quats=g.quats, sh=red.repeat(150, 1)[:, None, :],
                                opacities=torch.full((150,), 3.0), sh_t=sh_t, opacity_t=torch.zeros(150, TEMPORAL_TERMS)))
    return tmp_path / "dynamic.safetensors"


@pytest.fixture
def lit_from_one_side(tmp_path) -> Path:
    """Opaque relightable Gaussians (core/kinds/relight.py) with no colour of their own (c_dc = 0)
    and a colour network that makes them red when the light is on the side of the viewer's azimuth
    0 and blue when it is on the other side (azimuth 180): c_θ = W2 softplus(W1 d_l), eq. 14, with
    one hidden unit per side (identity rotations: the primitives' frame is the world's)."""
    g = random_gaussians(150, extent=0.6, scale=0.15, seed=2)
    side = torch.tensor(light_at((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.0, 0.0, 1.0, 1.0).position)  # azimuth 0, up +z
    network = init_network(150, DEFAULT_COLOR_HIDDEN, seed=0)
    network["color_w1"].zero_()
    network["color_b1"].zero_()
    network["color_w1"][:, 0, 3:] = 6.0 * side    # softplus(6 d_l · side): the light on azimuth 0's side
    network["color_w1"][:, 1, 3:] = -6.0 * side   # ... on the other side
    network["color_w2"][:, 0, 0] = 0.15           # red from the first unit
    network["color_w2"][:, 2, 1] = 0.15           # blue from the second
    no_colour = rgb_to_sh_dc(torch.zeros(150, 3))[:, None, :]
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(150, 1)
    save_model(tmp_path / "relight.safetensors",
               RelightGaussians(means=g.means, log_scales=g.log_scales, quats=identity, sh=no_colour,
                                opacities=torch.full((150,), 3.0), **network))
    return tmp_path / "relight.safetensors"


def _moment(line: str) -> float:
    """The moment a frame log line says it shows."""
    return float(re.search(r" at time (\d+\.\d+)", line).group(1))


def _light(line: str) -> str:
    """The light a frame log line says it was drawn under."""
    return line.split("under a light at ")[1].split(" in ")[0]


CLICK = """(() => {{
    const button = [...document.querySelectorAll('button')].find(b => b.textContent.trim() === '{label}');
    if (button) button.click();
    return Boolean(button);
}})()"""


def test_play_advances_the_time_by_the_wall_time_and_loops(red_to_blue, lit_from_one_side, colourful_model,
                                                            monkeypatch):
    """Play moves the Time slider by (wall time since its last advance) / PLAY_SECONDS, rounded to
    the slider's step, from 1 back to 0; a slider the user moved plays on from there; Pause stops
    it. Only a dynamic model has it."""
    from radfield.delivery.view_scene import viewer_scene
    from radfield.delivery.viewer import PLAY_SECONDS, Viewer

    monkeypatch.setenv("RADFIELD_KERNELS", "torch")
    viewer = Viewer(viewer_scene(red_to_blue, asked={"time": Asked("--time", value=0.1)}), port=0, log=lambda line: None)
    try:
        assert viewer.play_button.label == "Play" and not viewer.playing
        viewer.advance_play(time.monotonic() + 1.0)
        assert viewer.time == pytest.approx(0.1)                        # not playing: the slider stays
        viewer.set_playing(True)
        assert viewer.play_button.label == "Pause"
        start = viewer.play_clock
        viewer.advance_play(start + 0.25 * PLAY_SECONDS)
        assert viewer.time == pytest.approx(0.35)
        viewer.advance_play(start + 0.251 * PLAY_SECONDS)             # less than a step: the slider stays
        assert viewer.time == pytest.approx(0.35)
        viewer.advance_play(start + 1.05 * PLAY_SECONDS)
        assert viewer.time == pytest.approx(0.15)                       # 1.15: looped from 1 back to 0
        viewer.time_slider.value = 0.6                                 # the user drags the slider
        viewer.advance_play(start + 1.15 * PLAY_SECONDS)
        assert viewer.time == pytest.approx(0.7)
        viewer.set_playing(False)
        assert viewer.play_button.label == "Play"
        viewer.advance_play(start + 2.0 * PLAY_SECONDS)
        assert viewer.time == pytest.approx(0.7)
    finally:
        viewer.server.stop()
    for other in (lit_from_one_side, colourful_model):   # relightable, static: no Play
        viewer = Viewer(viewer_scene(other), port=0, log=lambda line: None)
        try:
            assert viewer.play_button is None and viewer.time is None
        finally:
            viewer.server.stop()


def test_play_runs_the_time_in_headless_chromium(red_to_blue, tmp_path):
    """A real browser: the viewer of a dynamic model has a Play button; pressed, the server runs
    the Time slider by itself (frames at moments that advance), the browser's slider follows and
    its view turns from red towards blue; Pause stops the clock and draws a full-resolution frame."""
    with _viewer_in_chromium(red_to_blue, tmp_path, "--time", "0") as (log, devtools_port):
        _wait(lambda: log.find("(full) at time 0.00"), "a full frame at time 0")
        before = _middle_of_page(devtools_port, tmp_path / "t0.png")
        since = len(log.lines)
        assert _in_page(devtools_port, CLICK.format(label="Play")), "no Play button in the page"
        # half way through a pass (4 s a pass), so that Pause stops it well before it loops
        _wait(lambda: any(0.5 <= _moment(line) < 0.8 for line in _frames(log, since)), "Play to reach time 0.5")
        playing = [_moment(line) for line in _frames(log, since)]
        slider = float(_in_page(devtools_port, "document.querySelector('[role=slider][aria-valuemax=\"1\"]')"
                                               ".getAttribute('aria-valuenow')"))
        assert _in_page(devtools_port, CLICK.format(label="Pause")), "Play did not turn into Pause"
        paused = _wait(lambda: next((line for line in _frames(log, since) if "(full)" in line), None),
                       "a full frame once paused")
        after = _middle_of_page(devtools_port, tmp_path / "paused.png")
        still = _frames(log, log.lines.index(paused) + 1)
    # Play advanced the moment by itself, in steps, drawing small frames while it played
    assert len(set(playing)) >= 3 and playing == sorted(playing), playing
    assert not any("(full)" in line for line in _frames(log, since)[: len(playing)])
    assert slider >= 0.4, f"the browser's Time slider did not follow Play ({slider})"
    moment = _moment(paused)
    assert 0.5 <= moment < 1.0, f"paused at {moment}"
    assert all(_moment(line) == moment for line in still), still   # paused: the moment stays
    # the page shows the moment: red at 0, then blue (S = red + ξ (blue − red))
    assert _dominant(before, 0) > 0.1 and _dominant(before, 2) < 0.01
    blueness = lambda image: float((image[..., 2] - image[..., 0]).mean())
    assert blueness(after) - blueness(before) > 0.2, (blueness(before), blueness(after))
    if moment >= 0.6:
        assert _dominant(after, 2) > 0.1 and _dominant(after, 0) < 0.01


def test_light_azimuth_relights_the_page_in_headless_chromium(lit_from_one_side, tmp_path):
    """A real browser: the viewer of a relightable model has light sliders; moving the azimuth (the
    End key on its thumb: 180 degrees, from 0) makes the server draw the model lit from the other
    side, and the page turns from red to blue."""
    with _viewer_in_chromium(lit_from_one_side, tmp_path) as (log, devtools_port):
        first = _wait(lambda: next((line for line in _frames(log) if "(full)" in line), None), "a full frame")
        assert "under a light at" in first, first
        before = _middle_of_page(devtools_port, tmp_path / "azimuth0.png")
        since = len(log.lines)
        # the azimuth slider's thumb (it ends at 180; elevation's at 89): End moves it to 180
        assert _in_page(devtools_port, """(() => {
            const thumb = document.querySelector('[role=slider][aria-valuemax="180"]');
            if (!thumb) return false;
            thumb.focus();
            thumb.dispatchEvent(new KeyboardEvent('keydown', {key: 'End', bubbles: true}));
            return true;
        })()"""), "no light azimuth slider in the page"
        moved = _wait(lambda: next((line for line in _frames(log, since) if "(full)" in line
                                    and _light(line) != _light(first)), None), "a full frame under the moved light")
        after = _middle_of_page(devtools_port, tmp_path / "azimuth180.png")
    assert _dominant(before, 0) > 0.1 and _dominant(before, 2) < 0.01, "not lit from azimuth 0"
    assert _dominant(after, 2) > 0.1 and _dominant(after, 0) < 0.01, "not lit from azimuth 180"


def test_sigterm_stops_the_viewer_with_one_line(colourful_model):
    """A real `radfield view` process and a real SIGTERM: the server is stopped, one line, exit 0
    (it used to die without closing the server; with pycolmap imported, whose glog failure handler
    catches SIGTERM, it printed a 32-line stack dump: pycolmap is imported first when present)."""
    import importlib.util
    import signal

    preload = "import pycolmap; " if importlib.util.find_spec("pycolmap") is not None else ""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", "RADFIELD_KERNELS": "torch"}
    server = subprocess.Popen([sys.executable, "-c", f"{preload}from radfield.cli.main import main; main()", "view",
                               str(colourful_model), "--server", "--host", "127.0.0.1", "--port", "0"],
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
