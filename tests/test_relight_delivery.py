"""A relightable model delivered (issue 30, "Commands"): `radfield render --light / --light-dir /
--light-orbit`, light-orbit videos, `radfield export --light`, the viewer's light sliders, and
eval's per-light plot.

A relightable model drawn under a light is render() of the model with Camera.conditions["light"] set (its kind's
at_view), and exported under a light it is its kind's at_light (the static model of that lighting),
so every check compares with those. (Their options mistaken, and a static model's refusal of them:
test_conditions.py.)
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import imageio
import numpy as np
import pytest
import torch

from radfield.core import kinds
from radfield.core.geometry.cameras import Camera, Light, look_at
from radfield.core.kinds import random_gaussians, random_neural
from radfield.datasets.images import read_image
from radfield.datasets.scene import load_split
from radfield.evaluation import report
from radfield.delivery.export import as_gaussians
from radfield.model_formats.ply_3dgs import read_gaussian_ply
from radfield.model_file import load_model, save_model
from radfield.conditions import Asked
from radfield.conditions.light import light_angles, light_at, orbit_lights
from radfield.errors import RadfieldError
from radfield.pipeline.config import load_config

from shared_helpers import drawn, with_network


SIZE = 16
LIGHT_A, LIGHT_B = (3.0, 0.0, 1.0), (-1.0, 3.0, 2.0)


@pytest.fixture(scope="module")
def olat(tmp_path_factory, run_radfield):
    """A tiny relighting dataset (2 test cameras × 2 lights, 16 px) and relightable model files."""
    root = tmp_path_factory.mktemp("relight")
    assert run_radfield("demo-scene", "olat", "-o", root / "olat", "--size", SIZE, "--train-views", 3,
                        "--test-views", 2, "--lights", 2, "-q") == 0
    save_model(root / "relight.safetensors",
               with_network(random_neural(40, scale=0.35, extent=0.6, b2=1.5, w2_amplitude=0.4, seed=0), amplitude=0.6))
    save_model(root / "gaussian-relight.safetensors", with_network(random_gaussians(30, extent=0.6, scale=0.2, seed=3)))
    save_model(root / "static.safetensors", random_neural(20, extent=0.5, seed=4))
    return root


def split_cameras(olat) -> list[Camera]:
    """The olat dataset's test cameras, each with its light."""
    return load_split(olat / "olat", "test", load_config(None)["data"]).cameras


def close(png, expected) -> bool:
    """A written PNG (8 bits) is the float image rounded."""
    return np.abs(read_image(png)[..., :3] - expected).max() <= 0.5 / 255 + 1e-6


def test_render_light_draws_the_model_under_that_light(cli, olat, tmp_path):
    model = load_model(olat / "relight.safetensors")
    camera = split_cameras(olat)[0]
    assert [c.name for c in split_cameras(olat)] == ["r_000_l00", "r_000_l01", "r_001_l00", "r_001_l01"]
    images = {}
    for light in (LIGHT_A, LIGHT_B):
        out = tmp_path / f"{light}"
        code, stdout, err = cli("render", olat / "relight.safetensors", "-d", olat / "olat", "-o", out,
                                "--light", ",".join(map(str, light)), "--light-intensity", "9", "-q")
        assert code == 0, err
        # one image a camera, not one per light it was photographed under
        assert stdout.startswith("rendered 2 views under 1 light (16x16"), stdout
        assert sorted(p.name for p in out.iterdir()) == ["r_000.png", "r_001.png"]
        images[light] = read_image(out / "r_000.png")[..., :3]
        assert close(out / "r_000.png", drawn(model, camera.at(light=Light(position=light, intensity=9.0))))
    assert np.abs(images[LIGHT_A] - images[LIGHT_B]).max() > 0.1   # the lights differ
    # a directional light
    code, _, err = cli("render", olat / "relight.safetensors", "-d", olat / "olat", "-o", tmp_path / "sun",
                       "--light-dir", "0,0,-1", "--camera", camera.name, "-q")
    assert code == 0, err
    assert close(tmp_path / "sun" / "r_000.png", drawn(model, camera.at(light=Light(direction=(0, 0, -1)))))


def test_dataset_views_render_under_their_own_lights(cli, olat, tmp_path):
    model = load_model(olat / "relight.safetensors")
    cameras = split_cameras(olat)
    assert len({c.conditions["light"] for c in cameras}) == 4
    assert all(c.conditions["light"].position is not None for c in cameras)
    code, stdout, err = cli("render", olat / "relight.safetensors", "-d", olat / "olat", "-o", tmp_path / "own", "-q")
    assert code == 0, err
    assert stdout.startswith("rendered 4 images: 2 views under 4 lights"), stdout
    for camera in cameras:
        assert close(tmp_path / "own" / f"{camera.name}.png", drawn(model, camera))
    # the two lights of one camera give two images
    first, second = (read_image(tmp_path / "own" / f"{c.name}.png") for c in cameras[:2])
    assert cameras[0].c2w.equal(cameras[1].c2w) and np.abs(first - second).max() > 0.05


def test_light_orbit_circles_the_object_at_the_dataset_lights_distance(cli, olat, tmp_path):
    model = load_model(olat / "relight.safetensors")
    camera = split_cameras(olat)[0]
    code, stdout, err = cli("render", olat / "relight.safetensors", "-d", olat / "olat", "-o", tmp_path / "orbit",
                            "--camera", camera.name, "--light-orbit", "5", "--video", tmp_path / "orbit.mp4", "-q")
    assert code == 0, err
    assert stdout.startswith("rendered 5 images: 1 view under 5 lights"), stdout
    pngs = sorted((tmp_path / "orbit").glob("*.png"))
    assert [p.name for p in pngs] == [f"r_000_l{k:04d}.png" for k in range(5)]   # the light named once
    reader = imageio.get_reader(tmp_path / "orbit.mp4", "ffmpeg")
    frames = [frame for frame in reader]
    reader.close()
    assert len(frames) == 5 and frames[0].shape == (SIZE, SIZE, 3)
    images = [read_image(p)[..., :3] for p in pngs]
    assert max(np.abs(images[0] - image).max() for image in images[1:]) > 0.1   # the light moves
    # the lights: the demo scene's lie on a sphere of radius 2.75 about the origin, its mesh's box
    # centre is near it; the orbit keeps the dataset lights' mean distance about that centre
    from radfield.datasets.bounds import MESH, object_bounds

    train = load_split(olat / "olat", "test", load_config(None)["data"]).cameras
    bounds = object_bounds(train, olat / "olat" / MESH)
    centre = (bounds.low + bounds.high) / 2
    mean_distance = np.mean([np.linalg.norm(np.subtract(c.conditions["light"].position, centre)) for c in train])
    up = np.array([0.0, 0.0, 1.0])
    lights = orbit_lights([c.conditions["light"] for c in train], centre, up, 5)
    for k, light in enumerate(lights):
        assert np.linalg.norm(np.subtract(light.position, centre)) == pytest.approx(mean_distance)
    # the first image is the model under the orbit's first light (its up is the cameras' mean up)
    from radfield.core.geometry.camera_path import orbit_from_cameras

    first = orbit_lights([c.conditions["light"] for c in train], centre, orbit_from_cameras(train)["up"], 5)[0]
    assert close(pngs[0], drawn(model, camera.at(light=first)))
    # both move: an orbit of the camera paired one to one with the light's
    code, _, err = cli("render", olat / "relight.safetensors", "-d", olat / "olat", "-o", tmp_path / "both",
                       "--orbit", "3", "--light-orbit", "3", "-q")
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "both").iterdir()) == [f"orbit_{k:04d}_l{k:04d}.png" for k in range(3)]


@pytest.fixture(scope="module")
def relight_run(olat, tmp_path_factory, run_radfield):
    """A relightable run of the olat scene (5 steps: only its files matter here)."""
    run = tmp_path_factory.mktemp("relight-run") / "run"
    assert run_radfield("reconstruct", olat / "olat", "-o", run, "--set", "train.primitive=neural-relight",
                        "--set", "train.iterations=5", "--no-cage", "-q") == 0
    return run


def test_a_run_takes_its_dataset_lights_intensity(cli, olat, relight_run, tmp_path):
    """A light given without --light-intensity is as bright as the dataset's lights (the olat
    scene's: 2.75² = 7.5625), in render, export and view alike."""
    cameras = split_cameras(olat)
    mean = sum(c.conditions["light"].intensity for c in cameras) / len(cameras)
    assert mean == pytest.approx(7.5625)
    for name, args in (("own", []), ("given", ["--light-intensity", mean]), ("one", ["--light-intensity", 1])):
        code, _, err = cli("render", relight_run, "-o", tmp_path / name, "--light", "3,0,1", "-q", *args)
        assert code == 0, err
    default = read_image(tmp_path / "own" / "r_000.png")
    assert np.array_equal(default, read_image(tmp_path / "given" / "r_000.png"))
    assert np.abs(default - read_image(tmp_path / "one" / "r_000.png")).max() > 0.05
    code, stdout, err = cli("export", relight_run, "-f", "ply-3dgs", "-o", tmp_path / "run.ply", "--light", "3,0,1",
                            "--refine", "0")
    assert code == 0 and "light 3,0,1, light intensity 7.5625" in stdout, err
    model = load_model(relight_run / "train" / "model.safetensors")
    expected = as_gaussians(kinds.of(model).at_light(model, Light(position=(3, 0, 1), intensity=mean)), 1)
    assert torch.allclose(read_gaussian_ply(tmp_path / "run.ply").sh, expected.sh.float(), atol=1e-5)
    # the run's dataset says where the object is: a light inside it is refused
    code, _, err = cli("export", relight_run, "-f", "ply-3dgs", "-o", tmp_path / "in.ply", "--light", "0,0,0")
    assert code == 1 and "is inside the object's bounds" in err and err.count("\n") == 1, err
    assert not (tmp_path / "in.ply").exists()
    from radfield.delivery.view_scene import viewer_scene
    from radfield.delivery.viewer import Viewer

    viewer = Viewer(viewer_scene(relight_run), port=0, log=lambda line: None)
    try:   # no --light: the dataset lights' mean distance (about the model's centre) and intensity
        distance = np.mean([math.dist(c.conditions["light"].position, viewer.centre) for c in
                            load_split(olat / "olat", "all", load_config(None)["data"]).cameras])
        assert viewer.light.intensity == pytest.approx(mean)
        assert math.dist(viewer.light.position, viewer.centre) == pytest.approx(distance)
    finally:
        viewer.server.stop()


def test_light_angles_round_trip():
    centre, up = np.array([0.1, -0.2, 0.3]), np.array([0.0, 0.3, 1.0])
    light = light_at(centre, up, 40.0, 25.0, 2.5, 4.0)
    assert light_angles(centre, up, light) == pytest.approx((40.0, 25.0, 2.5))
    sun = light_at(centre, up, -120.0, 60.0, None, 1.0)
    assert sun.position is None and light_angles(centre, up, sun)[:2] == pytest.approx((-120.0, 60.0))


# --- eval: the per-light plot -----------------------------------------------------------------------


def test_eval_plots_the_psnr_of_each_light_and_the_report_links_it(cli, olat, tmp_path):
    code, _, err = cli("eval", olat / "relight.safetensors", "--dataset", olat / "olat", "-o", tmp_path / "report", "-q")
    assert code == 0, err
    text = (tmp_path / "report" / "report.md").read_text()
    section = text[text.index("## Per light"):]
    assert section.index("![PSNR per light](figures/psnr_per_light.png)") < section.index("| light |")
    plot = cv2.imread(str(tmp_path / "report" / "figures" / "psnr_per_light.png"))
    assert plot is not None and plot.shape[0] > 200 and plot.shape[1] > 400 and plot.std() > 0
    assert not (tmp_path / "report" / "figures" / "psnr_over_time.png").exists()


def test_the_light_plot_places_each_light_about_the_object():
    per_light = [{"position": [3.0, 0.0, 4.0], "intensity": 9.0, "views": 2, "psnr": 25.0, "ssim": 0.9, "lpips": None},
                 {"position": [0.0, -2.0, 1.0], "intensity": 9.0, "views": 1, "psnr": 28.0, "ssim": 0.9, "lpips": None},
                 {"direction": [0.0, 0.0, -1.0], "intensity": 1.0, "views": 1, "psnr": 22.0, "ssim": 0.8, "lpips": None}]
    # about (0, 0, 1) with +z up: 45° up towards +x, level towards −y, and a sun straight overhead
    angles = report.light_angles(per_light, (0.0, 0.0, 1.0), (0.0, 0.0, 1.0))
    assert angles[0] == pytest.approx((0.0, 45.0)) and angles[1] == pytest.approx((-90.0, 0.0))
    assert angles[2][1] == pytest.approx(90.0)
    plot = cv2.imdecode(np.frombuffer(report.light_plot(per_light, (0.0, 0.0, 1.0), (0.0, 0.0, 1.0)), np.uint8),
                        cv2.IMREAD_COLOR)
    assert plot is not None and plot.std() > 0


def test_a_dataset_without_lights_leaves_a_relightable_model_unlit(cli, olat, tmp_path):
    code, _, err = cli("demo-scene", "blobs", "-o", tmp_path / "blobs", "--size", SIZE, "--train-views", 2,
                       "--test-views", 2, "-q")
    assert code == 0, err
    code, _, err = cli("render", olat / "relight.safetensors", "-d", tmp_path / "blobs", "-o", tmp_path / "out", "-q")
    assert code == 1 and "this model is relightable (neural-relight): give a light for the test views" in err, err
    assert err.count("\n") == 1 and not (tmp_path / "out").exists()
    code, _, err = cli("render", olat / "relight.safetensors", "-d", tmp_path / "blobs", "-o", tmp_path / "out",
                       "--light-orbit", "3", "-q")
    assert code == 1 and "--light-orbit circles the dataset's lights: the dataset has none" in err, err
    code, _, err = cli("render", olat / "relight.safetensors", "-d", tmp_path / "blobs", "-o", tmp_path / "out",
                       "--light", "3,0,1", "-q")   # a light of its own lights every view
    assert code == 0, err


def test_export_light_writes_that_lighting(cli, olat, tmp_path):
    model = load_model(olat / "relight.safetensors")
    written = {}
    for light in (LIGHT_A, LIGHT_B):
        out = tmp_path / f"{light}.ply"
        code, stdout, err = cli("export", olat / "relight.safetensors", "-f", "ply-3dgs", "-o", out,
                                "--light", ",".join(map(str, light)), "--refine", "0")
        assert code == 0, err
        assert f"light {','.join(f'{x:g}' for x in light)}, light intensity 1" in stdout
        written[light] = read_gaussian_ply(out)
        expected = as_gaussians(kinds.of(model).at_light(model, Light(position=light)), 1)
        assert len(written[light]) == len(expected)
        for name in ("means", "log_scales", "opacities", "sh"):   # at_light's SH is of degree 3, the PLY's
            assert torch.allclose(getattr(written[light], name), getattr(expected, name).float(), atol=1e-5), name
    assert (written[LIGHT_A].sh - written[LIGHT_B].sh).abs().max() > 0.1   # the colour follows the light
    # relightable Gaussians under one light are Gaussians: written exactly
    gaussians = load_model(olat / "gaussian-relight.safetensors")
    code, stdout, err = cli("export", olat / "gaussian-relight.safetensors", "-f", "ply-3dgs", "-o", tmp_path / "g.ply",
                            "--light-dir", "0,0,-1", "--light-intensity", "2")
    assert code == 0 and "from gaussian-relight, light direction 0,0,-1" in stdout, err
    exact = kinds.of(gaussians).at_light(gaussians, Light(direction=(0, 0, -1), intensity=2.0))
    back = read_gaussian_ply(tmp_path / "g.ply")
    assert torch.allclose(back.sh, exact.sh.float(), atol=1e-6) and torch.allclose(back.opacities, exact.opacities)


def test_viewer_light_sliders(olat, tmp_path):
    """The viewer of a relightable model has light sliders; its frames are the model under the
    sliders' light (no browser needed: the server renders what it streams)."""
    from radfield.delivery.view_scene import viewer_scene
    from radfield.delivery.viewer import Viewer

    model = load_model(olat / "relight.safetensors")
    start = Light(position=LIGHT_A, intensity=9.0)
    viewer = Viewer(viewer_scene(olat / "relight.safetensors", asked={"light": Asked("--light", value=start, settings={"intensity": None})}), port=0, log=lambda line: None)
    camera = Camera(20.0, 20.0, 8.0, 8.0, SIZE, SIZE, look_at((2.5, 0.5, 0.8), (0, 0, 0)))
    at = lambda light: (torch.from_numpy(drawn(model, camera.at(light=light))) * 255).round().numpy()
    try:
        assert viewer.relightable and len(viewer.light_sliders) == 3 and viewer.light == start
        assert np.array_equal(viewer.render_view(camera), at(start))
        azimuth, elevation, distance = light_angles(viewer.centre, viewer.up, start)
        viewer.light_sliders[0].value = azimuth + 180.0 if azimuth < 0 else azimuth - 180.0   # the other side
        moved = viewer.light
        assert moved.intensity == 9.0 and math.dist(moved.position, viewer.centre) == pytest.approx(distance)
        assert light_angles(viewer.centre, viewer.up, moved)[1] == pytest.approx(elevation)
        assert np.array_equal(viewer.render_view(camera), at(moved))
        assert np.abs(at(start) - at(moved)).max() > 20
    finally:
        viewer.server.stop()
    # a model file without --light: a light at 45 degrees lighting the centre with irradiance 1
    viewer = Viewer(viewer_scene(olat / "relight.safetensors"), port=0, log=lambda line: None)
    try:
        light = viewer.light
        distance = math.dist(light.position, viewer.centre)
        assert light.intensity == pytest.approx(distance**2)
        assert light_angles(viewer.centre, viewer.up, light)[1] == pytest.approx(45.0)
    finally:
        viewer.server.stop()
    viewer = Viewer(viewer_scene(olat / "static.safetensors"), port=0, log=lambda line: None)
    try:
        assert not viewer.relightable and viewer.light is None
    finally:
        viewer.server.stop()
    with pytest.raises(RadfieldError, match="--light is for a relightable model"):
        viewer_scene(olat / "static.safetensors", asked={"light": Asked("--light", value=start, settings={"intensity": None})})


def test_bake_measures_the_colour_each_view_composites(olat):
    """bake's coverage W_iv (delivery/bake.py) of a relightable model is that of the static model
    each view draws (its at_view): not scaled by the light's irradiance, and not zero where the
    network darkens a primitive's colour to the clamp at 0 (which the probe in `sh` alone met)."""
    from radfield.delivery.bake import coverage

    model = load_model(olat / "relight.safetensors")
    dark = replace(model, color_b2=model.color_b2 - 3.0)   # every view's colour below 0: clamped to black
    for prims in (model, dark):
        for camera in split_cameras(olat):
            seen = kinds.of(prims).at_view(prims, camera)
            expected = coverage(seen, [camera])
            assert float(expected.max()) > 0.05   # the model covers pixels in this view
            torch.testing.assert_close(coverage(prims, [camera]), expected, rtol=1e-5, atol=1e-7)
