"""A dynamic model delivered (issue 29, "Commands"): `radfield render --time / --times`, time-lapse
videos, `radfield export --time`, and the viewer's time slider.

A dynamic model drawn at a moment is exactly the static model its kind returns for that moment
(kinds/dynamic.py: at_time), so every check compares with render()/export of at_time(model, T).
(Their options mistaken, and a static model's refusal of them: test_conditions.py.)
"""

from __future__ import annotations

import base64
import json
import math
import os
import shutil
import time

import imageio
import numpy as np
import pytest
import torch

from radfield.core import kinds
from radfield.core.kinds import DynamicNeuralPrimitives, random_gaussians, random_neural
from radfield.core.kinds.dynamic import TEMPORAL_TERMS
from radfield.datasets.images import read_image
from radfield.datasets.scene import load_split
from radfield.conditions import Asked
from radfield.delivery.content import gaussians_for, under_conditions
from radfield.delivery.export import Content, as_gaussians, nerfstudio_transforms, view_cameras
from radfield.model_formats.ply_3dgs import read_gaussian_ply
from radfield.model_file import load_model, save_model
from radfield.conditions.time import parse_times
from radfield.errors import RadfieldError
from radfield.pipeline.config import load_config

from shared_helpers import drawn

SIZE = 16


def dynamic_model(seed: int = 0) -> DynamicNeuralPrimitives:
    """Neural primitives around the origin whose colour and density change clearly over time."""
    base = random_neural(40, scale=0.35, extent=0.6, b2=1.5, w2_amplitude=0.4, seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    n, hidden = len(base), base.hidden
    tensors = {k: getattr(base, k) for k in ("means", "log_scales", "quats", "sh", "w1", "b1", "w2", "b2")}
    return DynamicNeuralPrimitives(**tensors, omega0=base.omega0, window=base.window, time_frequency=2 * math.pi,
                                   w_t=(torch.rand(n, hidden, generator=g) * 2 - 1) * 0.1,
                                   sh_t=torch.randn(n, TEMPORAL_TERMS, 3, generator=g))


@pytest.fixture(scope="module")
def smoke(tmp_path_factory, run_radfield):
    """A tiny dynamic dataset (2 test cameras × 3 moments, 16 px) and a dynamic model file."""
    root = tmp_path_factory.mktemp("dynamic")
    assert run_radfield("demo-scene", "smoke", "-o", root / "smoke", "--size", SIZE, "--times", 3,
                        "--train-views", 3, "--test-views", 2, "-q") == 0
    save_model(root / "dynamic.safetensors", dynamic_model())
    return root


def test_render_time_draws_that_moment_once_a_camera(cli, smoke, tmp_path):
    model = load_model(smoke / "dynamic.safetensors")
    cameras = load_split(smoke / "smoke", "test", load_config(None)["data"]).cameras
    assert [c.name for c in cameras] == ["r_000_t000", "r_000_t001", "r_000_t002", "r_001_t000", "r_001_t001", "r_001_t002"]
    images = {}
    for t in (0.2, 0.8):
        out = tmp_path / f"t{t}"
        code, stdout, err = cli("render", smoke / "dynamic.safetensors", "-d", smoke / "smoke", "-o", out, "--time", t, "-q")
        assert code == 0, err
        # one image a camera, not one per recorded moment of it (6 images, 3 of them the same, before)
        assert stdout.startswith("rendered 2 views at 1 moment (16x16"), stdout
        assert sorted(p.name for p in out.iterdir()) == ["r_000.png", "r_001.png"]
        images[t] = read_image(out / "r_000.png")[..., :3]
        static = kinds.of(model).at_time(model, t)    # the static model of that moment
        assert np.abs(images[t] - drawn(static, cameras[0])).max() <= 0.5 / 255 + 1e-6
    assert np.abs(images[0.2] - images[0.8]).max() > 0.1   # the moments differ
    # without --time every view is drawn at its own time: r_000_t002 shows time 1
    code, _, err = cli("render", smoke / "dynamic.safetensors", "-d", smoke / "smoke", "-o", tmp_path / "own", "-q")
    assert code == 0, err
    own = next(c for c in cameras if c.conditions.get("time") == 1.0)
    code, _, err = cli("render", smoke / "dynamic.safetensors", "-d", smoke / "smoke", "-o", tmp_path / "one",
                       "--time", "1", "--camera", own.name, "-q")
    assert code == 0, err
    camera = own.name.rpartition("_")[0]   # r_000_t002: the camera r_000, named once
    assert [p.name for p in (tmp_path / "one").iterdir()] == [f"{camera}.png"]
    assert np.array_equal(read_image(tmp_path / "own" / f"{own.name}.png"), read_image(tmp_path / "one" / f"{camera}.png"))
    code, stdout, err = cli("render", smoke / "dynamic.safetensors", "-d", smoke / "smoke", "-o", tmp_path / "all", "-q")
    assert code == 0 and stdout.startswith("rendered 6 images: 2 views at 3 moments (16x16"), stdout


def test_render_times_writes_every_camera_at_every_moment(cli, smoke, tmp_path):
    code, stdout, err = cli("render", smoke / "dynamic.safetensors", "-d", smoke / "smoke", "-o", tmp_path / "many",
                            "--times", "0:1:3", "-q")
    assert code == 0, err
    names = sorted(p.name for p in (tmp_path / "many").iterdir())
    assert names == [f"r_00{v}_t{k:04d}.png" for v in range(2) for k in range(3)]   # the moment named once
    assert stdout.startswith("rendered 6 images: 2 views at 3 moments"), stdout
    code, _, err = cli("render", smoke / "dynamic.safetensors", "-d", smoke / "smoke", "-o", tmp_path / "half",
                       "--time", "0.5", "--camera", "r_000", "-q")
    assert code == 0, err
    assert np.array_equal(read_image(tmp_path / "many" / "r_000_t0001.png"), read_image(tmp_path / "half" / "r_000.png"))
    code, stdout, err = cli("render", smoke / "dynamic.safetensors", "-d", smoke / "smoke", "-o", tmp_path / "lapse",
                            "--camera", "r_001_t002", "--times", "0:1:4", "-q")
    assert code == 0 and stdout.startswith("rendered 4 images: 1 view at 4 moments"), stdout
    assert sorted(p.name for p in (tmp_path / "lapse").iterdir()) == [f"r_001_t{k:04d}.png" for k in range(4)]


def test_time_lapse_videos(cli, smoke, tmp_path):
    # an orbit while time runs: its frames and the moments paired one to one
    code, _, err = cli("render", smoke / "dynamic.safetensors", "-d", smoke / "smoke", "-o", tmp_path / "orbit",
                       "--orbit", "4", "--times", "0:1:4", "--video", tmp_path / "orbit.mp4", "-q")
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "orbit").iterdir()) == [f"orbit_{k:04d}_t{k:04d}.png" for k in range(4)]
    reader = imageio.get_reader(tmp_path / "orbit.mp4", "ffmpeg")
    frames = [frame for frame in reader]
    reader.close()
    assert len(frames) == 4 and frames[0].shape == (SIZE, SIZE, 3)
    # a fixed camera (a view of the split) while time runs
    code, _, err = cli("render", smoke / "dynamic.safetensors", "-d", smoke / "smoke", "-o", tmp_path / "fixed",
                       "--camera", "0", "--times", "0:1:5", "--video", tmp_path / "fixed.mp4", "-q")
    assert code == 0, err
    pngs = sorted((tmp_path / "fixed").glob("*.png"))
    assert len(pngs) == 5
    reader = imageio.get_reader(tmp_path / "fixed.mp4", "ffmpeg")
    frames = [frame for frame in reader]
    reader.close()
    assert len(frames) == 5
    images = [read_image(p)[..., :3] for p in pngs]
    assert np.abs(images[0] - images[-1]).max() > 0.1                                    # time runs
    for k, frame in enumerate(frames):   # the video holds the frames in order (lossy at 16 px: the nearest one)
        errors = [np.abs(frame / 255.0 - image).mean() for image in images]
        assert int(np.argmin(errors)) == k, errors


def test_parse_times():
    assert parse_times("0:1:5") == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert parse_times("0.3:0.3:1") == [0.3]
    assert parse_times("1:0:3") == [1.0, 0.5, 0.0]   # backwards in time


def test_export_time_writes_that_moment(cli, smoke, tmp_path):
    model = load_model(smoke / "dynamic.safetensors")
    moments = {}
    for t in (0.0, 0.6):
        out = tmp_path / f"m{t}.ply"
        code, stdout, err = cli("export", smoke / "dynamic.safetensors", "-f", "ply-3dgs", "-o", out, "--time", t, "--refine", "0")
        assert code == 0, err
        assert f"time {t:g}" in stdout
        moments[t] = read_gaussian_ply(out)
        expected = as_gaussians(kinds.of(model).at_time(model, t), 1)   # moment matching of that moment's model
        assert len(moments[t]) == len(expected)
        for name in ("means", "log_scales", "opacities"):
            assert torch.allclose(getattr(moments[t], name), getattr(expected, name).float(), atol=1e-5), name
        assert torch.allclose(moments[t].sh[:, 0], expected.sh[:, 0].float(), atol=1e-5)   # the PLY pads bands 1-3
    assert (moments[0.0].sh[:, 0] - moments[0.6].sh[:, 0]).abs().max() > 0.1   # the colour moved with time
    code, stdout, err = cli("export", smoke / "dynamic.safetensors", "-f", "points", "-o", tmp_path / "p.ply", "--time", "0.6")
    assert code == 0, err
    # a dynamic Gaussian model's moment is written exactly: the opacity logit and colour of T
    red_to_blue(tmp_path / "gaussians.safetensors")
    gaussians = load_model(tmp_path / "gaussians.safetensors")
    code, stdout, err = cli("export", tmp_path / "gaussians.safetensors", "-f", "ply-3dgs", "-o", tmp_path / "g.ply", "--time", "0.5")
    assert code == 0 and "from gaussian-dynamic, time 0.5" in stdout, err
    written, expected = read_gaussian_ply(tmp_path / "g.ply"), kinds.of(gaussians).at_time(gaussians, 0.5)
    assert torch.allclose(written.opacities, expected.opacities) and torch.allclose(written.sh[:, 0], expected.sh[:, 0])


def timed_views(smoke) -> dict[str, list[dict]]:
    """scene.json-like VIEW dicts (with their times) of the smoke dataset's splits."""
    views = {}
    for split in ("train", "test"):
        for camera in load_split(smoke / "smoke", split, load_config(None)["data"]).cameras:
            views.setdefault(split, []).append({
                "name": camera.name, "image": f"/x/{camera.name}.png", "fx": camera.fx, "fy": camera.fy,
                "cx": camera.cx, "cy": camera.cy, "width": camera.width, "height": camera.height,
                "c2w": camera.c2w.tolist(), "file_width": camera.width, "file_height": camera.height,
                "distortion": None, "time": camera.conditions["time"]})
    return views


def test_refined_export_of_a_run_refines_against_that_moment(smoke):
    """A dynamic run's export: the refinement's teacher is the static model of T, whatever times
    the run's cameras carry, so it refines exactly as the static model of T does from the same
    cameras without times; without a moment a dynamic model reaches no conversion."""
    model = load_model(smoke / "dynamic.safetensors")
    views = timed_views(smoke)
    assert {c.conditions.get("time") for c in view_cameras(views["train"])} == {0.0, 0.5, 1.0}
    with pytest.raises(RadfieldError, match="give a time"):
        under_conditions(Content(model=model, views=views, source="run"), "ply-3dgs", {})
    settings = {"background": (1.0, 1.0, 1.0), "extent": 1.0, "source": "run"}
    dynamic = Content(model=model, views=views, **settings)
    assert under_conditions(dynamic, "ply-3dgs", {"time": Asked("--time", value=0.3)}) == {"time": 0.3}
    untimed = {split: [{k: v for k, v in view.items() if k != "time"} for view in split_views]
               for split, split_views in views.items()}
    static = Content(model=kinds.of(model).at_time(model, 0.3), views=untimed, **settings)
    made = [gaussians_for(content, "ply-3dgs", 1, 20) for content in (dynamic, static)]
    # measured once a camera (2 test cameras × 3 moments: 2 views, not the 6 duplicates)
    assert made[0].fidelity == made[1].fidelity and made[0].fidelity[1:] == (2, "test")
    for name in ("means", "log_scales", "quats", "opacities", "sh"):
        assert torch.equal(getattr(dynamic.model, name), getattr(static.model, name)), name
    # and that moment's model is not any moment's: the Gaussians of T = 0.3 are not those of T = 0.9
    other = Content(model=model, views=views, **settings)
    under_conditions(other, "ply-3dgs", {"time": Asked("--time", value=0.9)})
    gaussians_for(other, "ply-3dgs", 1, 20)
    assert not torch.equal(other.model.sh, dynamic.model.sh)


def test_exported_cameras_keep_their_times(smoke):
    frames = nerfstudio_transforms(timed_views(smoke))["frames"]
    assert sorted({f["time"] for f in frames}) == [0.0, 0.5, 1.0]


def test_viewer_time_slider(smoke, tmp_path):
    """The viewer of a dynamic model has a Time slider; its frames are the model at the slider's
    moment (no browser needed: the server renders what it streams)."""
    from radfield.core.geometry.cameras import Camera, look_at
    from radfield.delivery.view_scene import viewer_cameras, viewer_scene
    from radfield.delivery.viewer import Viewer

    model = load_model(smoke / "dynamic.safetensors")
    scene = viewer_scene(smoke / "dynamic.safetensors", asked={"time": Asked("--time", value=0.25)})
    viewer = Viewer(scene, port=0, log=lambda line: None)
    try:
        camera = Camera(20.0, 20.0, 8.0, 8.0, SIZE, SIZE, look_at((2.5, 0.5, 0.8), (0, 0, 0)))
        assert viewer.time_slider is not None and viewer.time == pytest.approx(0.25)
        at = lambda t: (torch.from_numpy(drawn(kinds.of(model).at_time(model, t), camera)) * 255).round().numpy()
        assert np.array_equal(viewer.render_view(camera), at(0.25))
        viewer.time_slider.value = 0.75
        assert np.array_equal(viewer.render_view(camera), at(0.75))
        assert np.abs(at(0.25) - at(0.75)).max() > 20
    finally:
        viewer.server.stop()
    static = tmp_path / "gaussians.safetensors"
    save_model(static, random_gaussians(10, seed=1, extent=0.5))
    viewer = Viewer(viewer_scene(static), port=0, log=lambda line: None)
    try:
        assert viewer.time_slider is None and viewer.time is None
    finally:
        viewer.server.stop()
    with pytest.raises(RadfieldError, match="--time is for a dynamic model"):
        viewer_scene(static, asked={"time": Asked("--time", value=0.5)})
    # a dynamic dataset photographs each camera at every moment: one frustum a pose
    assert len(viewer_cameras(timed_views(smoke))) == 5 and len(view_cameras(timed_views(smoke)["train"])) == 9


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
WAIT = 90.0   # seconds, upper bound of every wait (the machine may be busy)


def red_to_blue(path):
    """Opaque dynamic Gaussians that are red at time 0 and blue at time 1 (S(ξ) = S0 + a_1 ξ, eq. 10)."""
    from radfield.core.kinds import DynamicGaussians
    from radfield.core.splat.sh import rgb_to_sh_dc

    g = random_gaussians(150, extent=0.6, scale=0.15, seed=2)
    red, blue = rgb_to_sh_dc(torch.tensor([[1.0, 0.1, 0.1]])), rgb_to_sh_dc(torch.tensor([[0.1, 0.2, 1.0]]))
    sh_t = torch.zeros(150, TEMPORAL_TERMS, 3)
    sh_t[:, 0] = blue - red
    save_model(path, DynamicGaussians(means=g.means, log_scales=g.log_scales, quats=g.quats, sh=red.repeat(150, 1)[:, None, :],
                                      opacities=torch.full((150,), 3.0), sh_t=sh_t, opacity_t=torch.zeros(150, TEMPORAL_TERMS)))


def test_time_slider_in_headless_chromium(tmp_path):
    """A real browser: the viewer of a dynamic model shows a Time slider; moving it (the End key
    on its thumb) makes the server draw the last moment, and the page turns from red to blue."""
    import subprocess
    import sys
    import threading
    import urllib.request

    import cv2
    from websockets.sync.client import connect

    if CHROMIUM is None:
        if os.environ.get("CI") == "true":
            pytest.fail("chromium is missing (apt-get install -y chromium): the viewer test cannot run")
        pytest.skip("chromium is not installed (apt-get install -y chromium)")
    red_to_blue(tmp_path / "model.safetensors")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", "RADFIELD_KERNELS": "torch"}
    server = subprocess.Popen([sys.executable, "-m", "radfield", "view", str(tmp_path / "model.safetensors"), "--server",
                               "--host", "127.0.0.1", "--port", "0", "--resolution", "256", "--time", "0"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    lines: list[str] = []
    threading.Thread(target=lambda: [lines.append(line) for line in server.stderr], daemon=True).start()
    find = lambda text: next((line for line in lines if text in line), None)

    def wait(condition, what):
        end = time.monotonic() + WAIT
        while time.monotonic() < end:
            if value := condition():
                return value
            time.sleep(0.1)
        raise AssertionError(f"timed out waiting for {what}: {''.join(lines)}")

    browser = None
    try:
        wait(lambda: find("viewer: http://") or server.poll() is not None, "the viewer to start")
        assert server.poll() is None and "a time slider" in find("viewer: http://"), "".join(lines)
        port = int(find("viewer: http://").split("http://127.0.0.1:")[1].split()[0])
        profile = tmp_path / "chromium-profile"
        browser = subprocess.Popen([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu-sandbox",
                                    "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-first-run",
                                    "--disable-extensions", f"--user-data-dir={profile}",
                                    "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0",
                                    "--window-size=640,480", f"http://127.0.0.1:{port}/"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        active = profile / "DevToolsActivePort"
        devtools = int(wait(lambda: active.is_file() and active.read_text().split("\n")[0], "chromium's DevTools"))
        wait(lambda: find("(full) at time 0.00"), "a full frame at time 0")
        targets = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{devtools}/json/list", timeout=10).read())
        page = next(t for t in targets if t["type"] == "page")
        with connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=10) as ws:
            calls = iter(range(1, 1000))

            def call(method, **params):
                ident = next(calls)
                ws.send(json.dumps({"id": ident, "method": method, "params": params}))
                while (reply := json.loads(ws.recv(timeout=30))).get("id") != ident:
                    pass
                return reply["result"]

            def screenshot(name):
                time.sleep(3.0)   # the browser decodes the frame and fades it in as the scene background
                (tmp_path / name).write_bytes(base64.b64decode(call("Page.captureScreenshot", format="png")["data"]))
                image = cv2.cvtColor(cv2.imread(str(tmp_path / name)), cv2.COLOR_BGR2RGB).astype(np.float64) / 255
                h, w = image.shape[:2]
                return image[h // 4: 3 * h // 4, w // 4: 3 * w // 4]

            before = screenshot("t0.png")
            # the Time slider's thumb (it ends at 1; Resolution's at 2048): the End key moves it to 1
            moved = call("Runtime.evaluate", returnByValue=True, expression="""(() => {
                const thumb = document.querySelector('[role=slider][aria-valuemax="1"]');
                thumb.focus();
                thumb.dispatchEvent(new KeyboardEvent('keydown', {key: 'End', bubbles: true}));
                return document.body.innerText.includes('Time');
            })()""")
            assert moved["result"]["value"] is True, moved
            wait(lambda: find("(full) at time 1.00"), "a full frame at time 1 after the slider moved")
            after = screenshot("t1.png")
    finally:
        for proc in (browser, server):
            if proc is not None:
                proc.kill()
                proc.wait(timeout=30)
    for image, dominant, other in ((before, 0, 2), (after, 2, 0)):
        saturated = image.max(-1) - image.min(-1) > 0.4
        assert (saturated & (image.argmax(-1) == dominant)).mean() > 0.1, "the moment's colour is not shown"
        assert (saturated & (image.argmax(-1) == other)).mean() < 0.01, "the other moment's colour is shown"
