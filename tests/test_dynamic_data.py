"""Time in datasets (issue 29, data side): D-NeRF frames with a `time`, their bad times as one-line
errors, and `radfield demo-scene smoke` (an animated volume rendered by quadrature, checked against
an independent ray marcher). What time shares with the other view conditions (nerfstudio frames,
frames with and without one, scene.json, static datasets): test_conditions.py."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from radfield.demo import moving, smoke
from radfield.datasets.images import read_image
from radfield.datasets.readers import load_dataset
from radfield.demo.scenes import get_scene, orbit_cameras
from radfield.demo.raytrace import render_view
from radfield.demo.timelapse import generate_dynamic

from shared_helpers import frames, rewrite

TIMES = [0.0, 0.5, 1.0]


@pytest.fixture(scope="module")
def smoke_data(tmp_path_factory) -> Path:
    """The smoke scene at 16 px: 2 train + 1 test cameras, each at 3 times."""
    return smoke.generate_smoke(tmp_path_factory.mktemp("smoke") / "smoke", n_train=2, n_test=1, times=3, size=16)


# --- reading time -------------------------------------------------------------------------------


def test_smoke_is_a_d_nerf_dataset_whose_cameras_carry_their_time(smoke_data):
    train = frames(smoke_data / "transforms_train.json")
    assert len(train) == 2 * 3 and len(frames(smoke_data / "transforms_test.json")) == 3
    assert [f["time"] for f in train] == TIMES * 2
    dataset = load_dataset(smoke_data, "train")
    assert [cam.conditions.get("time") for cam in dataset.cameras] == TIMES * 2
    # one camera photographs every time: the same pose, other moments
    assert torch.equal(dataset.cameras[0].c2w, dataset.cameras[2].c2w)
    assert not torch.equal(dataset.cameras[0].c2w, dataset.cameras[3].c2w)
    assert [cam.conditions.get("time") for cam in load_dataset(smoke_data, "all", downscale=2).cameras] == TIMES * 3


# every case: (file to edit, how, frame named, what the message says)
BAD_TIMES = {
    "a string": ("transforms_train.json", lambda fs: fs[1].update(time="0.5"), 1, "'time' must be a number in [0, 1], not '0.5'"),
    "a bool": ("transforms_test.json", lambda fs: fs[2].update(time=True), 2, "'time' must be a number in [0, 1], not True"),
    "null": ("transforms_train.json", lambda fs: fs[3].update(time=None), 3, "not None"),
    "NaN": ("transforms_train.json", lambda fs: fs[5].update(time=float("nan")), 5, "not nan"),
    "above 1": ("transforms_train.json", lambda fs: fs[2].update(time=1.5), 2, "'time' 1.5 is outside [0, 1]"),
    "below 0": ("transforms_test.json", lambda fs: fs[1].update(time=-0.25), 1, "'time' -0.25 is outside [0, 1]"),
}


@pytest.mark.parametrize("case", BAD_TIMES)
def test_bad_times_are_one_line_naming_file_and_frame_and_nothing_is_written(case, smoke_data, tmp_path, cli):
    name, edit, index, message = BAD_TIMES[case]
    root = tmp_path / "bad"
    shutil.copytree(smoke_data, root)
    rewrite(root / name, edit)
    file_path = frames(root / name)[index]["file_path"]
    code, out, err = cli("reconstruct", root, "-o", tmp_path / "run")
    assert code == 1 and err.count("\n") == 1, err
    assert err.startswith(f"radfield: error: {root / name}: frames[{index}] ({file_path})"), err
    assert message.format(root=root) in err
    assert not (tmp_path / "run").exists()


# --- demo-scene smoke ---------------------------------------------------------------------------


def test_smoke_images_change_over_time_and_have_soft_edges_and_dense_cores(smoke_data):
    first, middle, last = (read_image(smoke_data / "train" / f"r_001_t{k:03d}.png") for k in range(3))
    assert first.shape == (16, 16, 4)
    assert np.abs(first - last).max() > 0.3 and np.abs(first - middle).max() > 0.1
    alphas = np.stack([read_image(path)[..., 3] for path in sorted((smoke_data / "train").glob("*.png"))])
    assert ((alphas > 0.05) & (alphas < 0.9)).mean() > 0.05        # semi-transparent edges
    assert alphas.max() > 0.97                                     # dense cores
    assert alphas[:, [0, -1], :].max() < 1 / 255 and alphas[:, :, [0, -1]].max() < 1 / 255  # nothing leaves the view
    description = json.loads((smoke_data / "scene.json").read_text())
    assert description["name"] == "smoke" and description["times"] == TIMES


def test_puffs_stay_inside_every_view_at_every_time():
    for xi in np.linspace(0, 1, 41):
        assert max(puff.extent_at(xi) for puff in smoke.PUFFS) < smoke.VIEW_RADIUS


def test_smoke_quadrature_has_converged_and_alpha_is_exact():
    camera = orbit_cameras(3, 1, 24, seed=1)[0][1]
    coarse, fine, finer = (smoke.render_smoke(camera, 0.7, segments=n)
                           for n in (8, smoke.SEGMENTS, 2 * smoke.SEGMENTS))
    assert np.abs(fine - finer).max() < 1e-3                        # far below 1/255
    assert np.abs(coarse[..., 3] - finer[..., 3]).max() < 1e-6     # opacity is closed form
    assert np.abs(coarse - finer).max() > 10 * np.abs(fine - finer).max()  # the check can fail


def march(origin: np.ndarray, direction: np.ndarray, xi: float, steps: int = 40000) -> np.ndarray:
    """Premultiplied RGBA of one ray by the plain midpoint rule on the densities as written
    (σ_k(x) = ρ exp(−½|S⁻¹Rᵀ(x − μ)|²)), independent of the renderer's closed forms."""
    l = (np.arange(steps) + 0.5) * (8.0 / steps)
    x = origin + l[:, None] * direction
    sigma = np.stack([p.density_at(xi) * np.exp(-0.5 * np.sum(
        ((x - p.centre_at(xi)) @ p.rotation_at(xi) / p.scales_at(xi)) ** 2, -1)) for p in smoke.PUFFS], -1)
    total = sigma.sum(-1)
    alpha = 1 - np.exp(-total * 8.0 / steps)
    transmittance = np.concatenate([[1.0], np.cumprod(1 - alpha)[:-1]])
    mix = (sigma @ np.array([p.colour for p in smoke.PUFFS])) / np.maximum(total, 1e-300)[:, None]
    colour = ((transmittance * alpha)[:, None] * mix).sum(0)
    return np.append(colour, 1 - np.prod(1 - alpha))


def test_smoke_matches_an_independent_ray_marcher():
    camera = orbit_cameras(3, 1, 16, seed=2)[0][0]
    image = smoke.render_smoke(camera, 0.4)
    c2w = camera.c2w.numpy()
    for row, col in [(8, 8), (6, 9), (9, 5), (4, 11), (11, 7), (7, 3), (0, 0)]:
        d = np.array([(col + 0.5 - camera.cx) / camera.fx, (row + 0.5 - camera.cy) / camera.fy, 1.0])
        d = c2w[:3, :3] @ (d / np.linalg.norm(d))
        np.testing.assert_allclose(image[row, col], march(c2w[:3, 3], d, 0.4), atol=1e-4)
    assert image[..., 3].max() > 0.5  # the pixels checked include solid smoke


def test_demo_scene_smoke_command(cli, tmp_path):
    out = tmp_path / "smoke"
    code, text, err = cli("demo-scene", "smoke", "-o", out, "--size", "8", "--train-views", "2", "--test-views", "1",
                          "--times", "2", "-q")
    assert code == 0, err
    assert f"wrote smoke: 2 train + 1 test cameras at 2 times (4 + 2 frames) of 8x8 to {out}" in text
    assert sorted(p.name for p in (out / "test").iterdir()) == ["r_000_t000.png", "r_000_t001.png"]
    code, _, err = cli("demo-scene", "blobs", "-o", tmp_path / "b", "--times", "3")
    assert code == 1 and "--times is for the dynamic scenes" in err and not (tmp_path / "b").exists()
    code, _, err = cli("demo-scene", "smoke", "-o", tmp_path / "s", "--deform", "twist")
    assert code == 1 and "--deform is for the static scenes" in err and not (tmp_path / "s").exists()
    code, _, err = cli("demo-scene", "fog", "-o", tmp_path / "f")
    assert code == 1 and "unknown demo scene 'fog'" in err and "smoke, moving" in err and not (tmp_path / "f").exists()


# --- demo-scene moving --------------------------------------------------------------------------


def test_moving_starts_as_the_objects_scene_and_its_shapes_move(tmp_path):
    camera = orbit_cameras(3, 1, 16, seed=0)[0][2]
    still = render_view(get_scene("objects"), camera)[0]
    np.testing.assert_allclose(moving.render(camera, 0.0), still, atol=1e-6)
    later = moving.render(camera, 1.0)
    assert np.abs(later - still).max() > 0.5                       # shapes moved
    assert ((later[..., 3] > 0) & (later[..., 3] < 1)).mean() < 0.2  # opaque: only edge pixels are partial
    shapes = moving.scene_at(0.6).primitives
    assert shapes[4] == get_scene("objects").primitives[4]         # the still rod
    assert all(max(np.linalg.norm(s.bounding_sphere[0]) + s.bounding_sphere[1] for s in moving.scene_at(xi).primitives)
               < smoke.VIEW_RADIUS for xi in np.linspace(0, 1, 11))
    out = generate_dynamic("moving", tmp_path / "moving", n_train=1, n_test=1, times=2, size=8)
    assert [f["time"] for f in frames(out / "transforms_test.json")] == [0.0, 1.0]
    assert [cam.conditions.get("time") for cam in load_dataset(out, "train").cameras] == [0.0, 1.0]


def test_held_out_times_put_every_test_frame_between_two_training_times(cli, tmp_path):
    out = tmp_path / "smoke"
    code, text, err = cli("demo-scene", "smoke", "-o", out, "--size", "8", "--train-views", "1", "--test-views", "2",
                          "--times", "3", "--held-out-times", "-q")
    assert code == 0, err
    assert "1 train + 2 test cameras at 3 times (test at the 2 times between) (3 + 4 frames)" in text
    train = sorted({f["time"] for f in frames(out / "transforms_train.json")})
    test = [f["time"] for f in frames(out / "transforms_test.json")]
    assert train == TIMES and test == [0.25, 0.75, 0.25, 0.75]
    assert json.loads((out / "scene.json").read_text())["test_times"] == [0.25, 0.75]
    camera = orbit_cameras(1, 2, 8, seed=0)[1][0]                     # test camera 0 at its second time, 0.75
    np.testing.assert_allclose(read_image(out / "test" / "r_000_t001.png"), smoke.render(camera, 0.75), atol=1 / 255)
    code, _, err = cli("demo-scene", "moving", "-o", tmp_path / "m", "--times", "1", "--held-out-times")
    assert code == 1 and "--held-out-times needs at least 2 times" in err and not (tmp_path / "m").exists()
    code, _, err = cli("demo-scene", "blobs", "-o", tmp_path / "b", "--held-out-times")
    assert code == 1 and "--held-out-times is for the dynamic scenes" in err and not (tmp_path / "b").exists()
