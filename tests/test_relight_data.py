"""Lights in datasets (issue 30, data side): NeRF-synthetic frames with a `light_position` or
`light_direction` (and `light_intensity`), their bad lights as one-line errors, the light moved by
the normalisation, the point light of the analytic ray tracer (1/r², hard shadows) and `radfield
demo-scene olat` and `olat-glossy` (its cast shadow and its highlight move with the light). What
a light shares with the other view conditions (nerfstudio frames, frames with and without one,
scene.json, static datasets): test_conditions.py."""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from radfield.datasets.images import read_image
from radfield.core.geometry.cameras import Camera, look_at
from radfield.demo.olat import LIGHT_RADIUS, PILLAR_RADIUS, PILLAR_TOP, generate_olat, olat_scene
from radfield.datasets.readers import load_dataset
from radfield.datasets.scene import read_dataset, scene_from_json
from radfield.demo.scenes import PointLight
from radfield.demo.static import generate_scene
from radfield.demo.raytrace import intersect, render_view, shade
from radfield.pipeline.config import load_defaults

from shared_helpers import frames, rewrite

CAMERAS, LIGHTS = 2, 3  # train cameras and lights per camera of the tiny olat scene


@pytest.fixture(scope="module")
def olat_data(tmp_path_factory) -> Path:
    """The olat scene at 16 px: 2 train + 1 test cameras, each under 3 lights; no mesh (so the
    object's bounds come from the cameras)."""
    return generate_olat(tmp_path_factory.mktemp("olat") / "olat", n_train=CAMERAS, n_test=1, lights=LIGHTS,
                         size=16, mesh=False)


@pytest.fixture(scope="module")
def olat_glossy_data(tmp_path_factory) -> Path:
    """The olat-glossy scene, written as olat_data is."""
    return generate_olat(tmp_path_factory.mktemp("olat_glossy") / "olat-glossy", n_train=CAMERAS, n_test=1,
                         lights=LIGHTS, size=16, mesh=False, name="olat-glossy")


@pytest.fixture(scope="module")
def blobs(tmp_path_factory) -> Path:
    return generate_scene("blobs", tmp_path_factory.mktemp("blobs") / "blobs", n_train=3, n_test=1, size=16, mesh=False)


# --- reading lights -----------------------------------------------------------------------------


def test_olat_frames_carry_point_lights_that_become_the_cameras_lights(olat_data):
    train = frames(olat_data / "transforms_train.json")
    assert len(train) == CAMERAS * LIGHTS and len(frames(olat_data / "transforms_test.json")) == LIGHTS
    cameras = load_dataset(olat_data, "train").cameras
    for frame, camera in zip(train, cameras):
        light = camera.conditions.get("light")
        assert light.position == tuple(frame["light_position"]) and light.direction is None
        assert light.intensity == frame["light_intensity"] == LIGHT_RADIUS**2
    # one camera under several lights: the same pose, other lights
    assert torch.equal(cameras[0].c2w, cameras[1].c2w) and cameras[0].conditions["light"] != cameras[1].conditions["light"]


def test_directional_lights_and_intensities_are_read(olat_data, tmp_path):
    root = tmp_path / "dir"
    shutil.copytree(olat_data, root)

    def directional(fs):
        for k, frame in enumerate(fs):
            frame["light_direction"] = [0.0, 0.0, -2.0 - k]   # not unit: normalised on load
            frame["light_intensity"] = 0.5 + k
            del frame["light_position"]

    for name in ("transforms_train.json", "transforms_test.json"):
        rewrite(root / name, directional)
    cameras = load_dataset(root, "train").cameras
    assert [cam.conditions.get("light").direction for cam in cameras] == [(0.0, 0.0, -1.0)] * len(cameras)
    assert [cam.conditions.get("light").intensity for cam in cameras] == [0.5 + k for k in range(len(cameras))]
    assert all(cam.conditions.get("light").position is None for cam in cameras)


def test_an_intensity_defaults_to_one(olat_data, tmp_path):
    root = tmp_path / "unit"
    shutil.copytree(olat_data, root)
    for name in ("transforms_train.json", "transforms_test.json"):
        rewrite(root / name, lambda fs: [f.pop("light_intensity") for f in fs])
    assert {cam.conditions.get("light").intensity for cam in load_dataset(root, "all").cameras} == {1.0}


# every case: (file to edit, how, frame named, what the message says)
BAD_LIGHTS = {
    "an intensity left without its light": ("transforms_train.json", lambda fs: fs[4].pop("light_position"), 4,
                                            "has no light but frames[0] has one"),
    "two numbers": ("transforms_train.json", lambda fs: fs[1].update(light_position=[1.0, 2.0]), 1,
                    "'light_position' must be three finite numbers [x, y, z], not [1.0, 2.0]"),
    "a string": ("transforms_test.json", lambda fs: fs[2].update(light_position="3 0 1"), 2,
                 "'light_position' must be three finite numbers"),
    "a bool": ("transforms_train.json", lambda fs: fs[3].update(light_position=[True, 0.0, 3.0]), 3,
               "'light_position' must be three finite numbers"),
    "NaN": ("transforms_train.json", lambda fs: fs[5].update(light_position=[float("nan"), 0.0, 3.0]), 5,
            "'light_position' must be three finite numbers"),
    "both kinds": ("transforms_train.json", lambda fs: fs[2].update(light_direction=[0.0, 0.0, -1.0]), 2,
                   "not both"),
    "a zero direction": ("transforms_test.json",
                         lambda fs: [f.update(light_direction=[0, 0, 0]) or f.pop("light_position") for f in fs], 0,
                         "'light_direction' must not be [0, 0, 0]"),
    "zero intensity": ("transforms_train.json", lambda fs: fs[1].update(light_intensity=0), 1,
                       "'light_intensity' must be a positive number, not 0"),
    "negative intensity": ("transforms_test.json", lambda fs: fs[1].update(light_intensity=-2.5), 1,
                           "'light_intensity' must be a positive number, not -2.5"),
    "inside the object": ("transforms_train.json", lambda fs: fs[3].update(light_position=[0.1, -0.2, 0.3]), 3,
                          "light_position [0.1, -0.2, 0.3] is inside the object's bounds (the ball of radius"),
}


@pytest.mark.parametrize("case", BAD_LIGHTS)
def test_bad_lights_are_one_line_naming_file_and_frame_and_nothing_is_written(case, olat_data, tmp_path, cli):
    name, edit, index, message = BAD_LIGHTS[case]
    root = tmp_path / "bad"
    shutil.copytree(olat_data, root)
    rewrite(root / name, edit)
    file_path = frames(root / name)[index]["file_path"]
    code, out, err = cli("reconstruct", root, "-o", tmp_path / "run")
    assert code == 1 and err.count("\n") == 1, err
    assert err.startswith(f"radfield: error: {root / name}: frames[{index}] ({file_path})"), err
    assert message.format(root=root) in err, err
    assert not (tmp_path / "run").exists()


def test_an_intensity_without_a_light_is_one_line(blobs, tmp_path, cli):
    root = tmp_path / "static"
    shutil.copytree(blobs, root)
    rewrite(root / "transforms_train.json", lambda fs: fs[1].update(light_intensity=2.0))
    code, _, err = cli("reconstruct", root, "-o", tmp_path / "run")
    assert code == 1 and err.count("\n") == 1, err
    assert err.startswith(f"radfield: error: {root / 'transforms_train.json'}: frames[1] (./train/r_1): "
                          "'light_intensity' without a 'light_position' or 'light_direction'"), err
    assert not (tmp_path / "run").exists()


def test_a_light_inside_the_mesh_box_is_refused_one_outside_it_is_not(olat_data, tmp_path, cli):
    """With a mesh.ply the bounds are its box: a light beside the objects but inside the box is
    refused; the same dataset without its inside light reads."""
    root = tmp_path / "mesh"
    shutil.copytree(olat_data, root)
    generate_olat(tmp_path / "with_mesh", n_train=1, n_test=1, lights=1, size=8)  # only for its mesh.ply
    shutil.copy(tmp_path / "with_mesh" / "mesh.ply", root / "mesh.ply")
    assert len(load_dataset(root, "all").views) == (CAMERAS + 1) * LIGHTS
    # (0.8, 0.8, 0.0): outside every shape, but inside the plinth's bounding box (|x|, |y| <= 0.85)
    rewrite(root / "transforms_test.json", lambda fs: fs[1].update(light_position=[0.8, 0.8, 0.0]))
    code, _, err = cli("reconstruct", root, "-o", tmp_path / "run")
    assert code == 1 and err.count("\n") == 1, err
    assert f"{root / 'transforms_test.json'}: frames[1] (./test/r_000_l01): light_position [0.8, 0.8, 0]" in err, err
    assert "of the dataset's mesh.ply" in err
    assert not (tmp_path / "run").exists()


# --- the normalisation moves a light ------------------------------------------------------------


def test_normalisation_moves_a_point_light_with_the_cameras_and_keeps_its_irradiance(olat_data):
    scene = scene_from_json(read_dataset(olat_data, load_defaults()["data"])[0], olat_data / "scene.json")
    norm = scene.normalization
    assert abs(norm.scale - 1 / 4.0) < 1e-9    # cameras at radius 4 about the origin
    camera = scene.cameras("train")[2]
    normalised = norm.camera(camera)
    position = torch.tensor(camera.conditions.get("light").position, dtype=torch.float64)
    moved = torch.tensor(normalised.conditions.get("light").position, dtype=torch.float64)
    torch.testing.assert_close(moved, norm.apply(position), rtol=0, atol=1e-12)
    # the light keeps its place relative to the camera: the same vector, scaled
    torch.testing.assert_close(moved - normalised.c2w[:3, 3], (position - camera.c2w[:3, 3]) * norm.scale)
    # intensity / r² at any point is the same in both frames
    for point in ([0.0, 0.0, 0.0], [0.3, -0.5, 0.2], [1.0, 1.0, -0.5]):
        x = torch.tensor(point, dtype=torch.float64)
        world = camera.conditions.get("light").intensity / (position - x).square().sum()
        frame = normalised.conditions.get("light").intensity / (moved - norm.apply(x)).square().sum()
        assert abs(world - frame) < 1e-12 * world
    assert normalised.conditions.get("light").intensity != camera.conditions.get("light").intensity


def test_normalisation_keeps_a_directional_light(olat_data, tmp_path):
    root = tmp_path / "dir"
    shutil.copytree(olat_data, root)
    for name in ("transforms_train.json", "transforms_test.json"):
        rewrite(root / name, lambda fs: [f.update(light_direction=[0.0, 0.6, -0.8]) or f.pop("light_position")
                                         for f in fs])
    scene = scene_from_json(read_dataset(root, load_defaults()["data"])[0], root / "scene.json")
    camera = scene.cameras("test")[0]
    assert scene.normalization.camera(camera).conditions.get("light") == camera.conditions.get("light")
    assert camera.conditions.get("light").direction == pytest.approx((0.0, 0.6, -0.8))


# --- the point light of the ray tracer ----------------------------------------------------------


def _plinth_hit(scene, target, offset=(0.4, 0.4)):
    """A ray from above onto the plinth's top at `target`: (origin, direction, t, normal, index)."""
    origin = np.array([target[0] + offset[0], target[1] + offset[1], 2.0])
    d = np.asarray(target) - origin
    d = (d / np.linalg.norm(d))[None]
    t, normal, index = intersect(scene, origin, d)
    assert index[0] == 0 and abs(t[0] * d[0, 2] + 2.0 - target[2]) < 1e-9   # the plinth, at the target
    return origin, d, t, normal, index


def test_a_point_light_falls_off_as_one_over_r_squared():
    scene = olat_scene()
    target = (0.6, -0.05, -0.39)   # the plinth's top, clear of every object's shadow from above
    origin, d, t, normal, index = _plinth_hit(scene, target)
    albedo = scene.primitives[0].material.albedo(np.zeros((1, 3)))[0]
    ambient = scene.lighting.ambient  # (1 + sky n_z)/(1 + sky) = 1 on the upward plinth top
    for height in (1.0, 2.0, 3.0):
        light = PointLight((target[0], target[1], target[2] + height), intensity=4.0)
        colour, _ = shade(scene, origin, d, t, normal, index, point_light=light)
        # n·l = 1 straight above; irradiance 4 / height²
        expected = albedo * (ambient + (1 - ambient) * 4.0 / height**2)
        np.testing.assert_allclose(colour[0], np.clip(expected, 0, 1), atol=1e-12)


def test_a_shadow_moves_with_the_point_light():
    scene = olat_scene()
    target = np.array([-0.35, -0.75, -0.39])   # the plinth's top beside the red sphere
    origin, d, t, normal, index = _plinth_hit(scene, target, offset=(0.0, -0.5))
    towards_sphere = np.array([-0.35, -0.3, -0.07]) - target                   # through its centre
    behind = PointLight(tuple(target + 2.5 * towards_sphere / np.linalg.norm(towards_sphere)), LIGHT_RADIUS**2)
    aside = PointLight((-0.35, -2.75, 0.5), LIGHT_RADIUS**2)   # a low light from the open side: lit
    dark = shade(scene, origin, d, t, normal, index, point_light=behind)[0][0]
    lit = shade(scene, origin, d, t, normal, index, point_light=aside)[0][0]
    albedo = scene.primitives[0].material.albedo(np.zeros((1, 3)))[0]
    np.testing.assert_allclose(dark, albedo * scene.lighting.ambient, atol=1e-12)   # ambient only
    assert lit.sum() > 2 * dark.sum()
    # without shadows the light behind the sphere would light it: the darkness is the sphere's shadow
    import dataclasses
    unshadowed = dataclasses.replace(scene, lighting=dataclasses.replace(scene.lighting, shadows=False))
    assert shade(unshadowed, origin, d, t, normal, index, point_light=behind)[0][0].sum() > 2 * dark.sum()


# --- demo-scene olat ----------------------------------------------------------------------------


# each OLAT demo scene: its fixture, its name and the synthetic scene it lights
OLAT_SCENES = {"olat": ("olat_data", "studio"), "olat-glossy": ("olat_glossy_data", "glossy")}


@pytest.mark.parametrize("name", OLAT_SCENES)
def test_olat_files_and_lights(name, request):
    fixture, base = OLAT_SCENES[name]
    olat_data = request.getfixturevalue(fixture)
    assert sorted(p.name for p in olat_data.iterdir()) == ["scene.json", "test", "train", "transforms_test.json",
                                                           "transforms_train.json"]
    assert len(list((olat_data / "train").glob("*.png"))) == CAMERAS * LIGHTS
    train = [tuple(f["light_position"]) for f in frames(olat_data / "transforms_train.json")]
    test = [tuple(f["light_position"]) for f in frames(olat_data / "transforms_test.json")]
    assert len(set(train)) == len(train) and len(set(test)) == len(test)   # a new light in every frame
    gap = min(math.dist(a, b) for a in test for b in train)
    assert gap > 0.1                                                        # no test light is a train light
    radii = [math.dist(p, (0, 0, 0)) for p in train + test]
    assert max(abs(r - LIGHT_RADIUS) for r in radii) < 1e-9
    assert sum(p[2] > 0 for p in train + test) > 0.8 * len(radii)           # mostly the upper hemisphere
    description = json.loads((olat_data / "scene.json").read_text())
    assert description["name"] == name and description["base"] == base and description["lights_per_camera"] == LIGHTS
    # the dataset reads as a relightable one: every camera carries its frame's light
    cameras = load_dataset(olat_data, "all").cameras
    assert [cam.conditions.get("light").position for cam in cameras] == train + test


@pytest.mark.parametrize("name", OLAT_SCENES)
def test_olat_pixels_of_one_camera_change_with_the_light(name, request):
    olat_data = request.getfixturevalue(OLAT_SCENES[name][0])
    images = np.stack([read_image(olat_data / "train" / f"r_001_l{j:02d}.png") for j in range(LIGHTS)])
    assert images.shape == (LIGHTS, 16, 16, 4)
    assert np.array_equal(images[0, ..., 3], images[1, ..., 3])   # same camera, same silhouette
    solid = images[0, ..., 3] > 0.999
    brightness = images[..., :3].sum(-1)[:, solid]
    # some pixel lit under one light and dark under another
    assert (brightness.max(0) > 3 * brightness.min(0)).any()
    assert np.abs(images[0] - images[1]).max() > 0.2


def test_demo_scene_olat_command(cli, tmp_path):
    out = tmp_path / "olat"
    code, stdout, err = cli("demo-scene", "olat", "-o", out, "--train-views", 1, "--test-views", 1, "--lights", 2,
                            "--size", 8, "-q")
    assert code == 0, err
    assert "1 train + 1 test cameras under 2 point lights each" in stdout
    assert len(frames(out / "transforms_train.json")) == 2 and (out / "mesh.ply").is_file()
    code, _, err = cli("demo-scene", "blobs", "-o", tmp_path / "b", "--lights", 2)
    assert code == 1 and "--lights is for the one-light-at-a-time scenes (olat, olat-glossy)" in err


def test_demo_scene_olat_glossy_command(cli, tmp_path):
    out = tmp_path / "glossy"
    code, stdout, err = cli("demo-scene", "olat-glossy", "-o", out, "--train-views", 1, "--test-views", 1,
                            "--lights", 2, "--size", 8, "-q")
    assert code == 0, err
    assert stdout.startswith("wrote olat-glossy: 1 train + 1 test cameras under 2 point lights each"), stdout
    assert len(frames(out / "transforms_test.json")) == 2 and (out / "mesh.ply").is_file()
    description = json.loads((out / "scene.json").read_text())
    assert description["base"] == "glossy"
    glossy_spheres = [p for p in description["primitives"] if p["type"] == "sphere"]
    assert len(glossy_spheres) == 2 and min(p["material"]["specular"] for p in glossy_spheres) >= 0.6
    assert min(p["material"]["shininess"] for p in glossy_spheres) >= 40
    code, _, err = cli("demo-scene", "olat-matte", "-o", tmp_path / "x")
    assert code == 1 and "olat, olat-glossy)" in err and err.count("\n") == 1, err


# --- olat-glossy: the cast shadow and the highlight move with the light --------------------------


def _camera(eye, target, size: int, half_width: float, up=(0.0, 0.0, 1.0)) -> Camera:
    """A size × size pinhole at `eye` looking at `target`, whose image spans ±half_width there."""
    focal = 0.5 * size * math.dist(eye, target) / half_width
    return Camera(focal, focal, size / 2, size / 2, size, size, look_at(eye, target, up))


def _centre_hits(scene, camera: Camera) -> np.ndarray:
    """The index of the primitive each pixel-centre ray hits (H, W), -1 on a miss."""
    j, i = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    d = np.stack([(j - camera.cx) / camera.fx, (i - camera.cy) / camera.fy, np.ones_like(i)], -1).reshape(-1, 3)
    c2w = camera.c2w.numpy()
    d = d @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return intersect(scene, c2w[:3, 3], d)[2].reshape(camera.height, camera.width)


def _lit(scene, camera: Camera, position) -> np.ndarray:
    """The view's RGB (H, W, 3) under a point light at `position` (the scene's intensity)."""
    rgba, _ = render_view(scene, camera, rng=np.random.default_rng(0), point_light=PointLight(position, LIGHT_RADIUS**2))
    return rgba[..., :3]


def test_olat_glossy_pillar_casts_a_shadow_on_the_slab_that_moves_with_the_light():
    """From above, lights west and east of the pillar: each darkens a band of slab pixels on the
    other side that the pillar's absence would light, and the two bands do not overlap."""
    import dataclasses

    scene = olat_scene("olat-glossy")
    pillar = scene.primitives[-1]
    assert pillar.radius == PILLAR_RADIUS and pillar.end[2] == PILLAR_TOP and pillar.material.specular == 0
    without_pillar = dataclasses.replace(scene, primitives=scene.primitives[:-1])
    camera = _camera((0.05, 0.05, 3.0), (0.05, 0.05, -0.39), 24, 1.0, up=(0.0, 1.0, 0.0))
    slab = _centre_hits(scene, camera) == 0
    shadows = []
    for light in ((-2.0, 0.05, 1.2), (2.0, 0.05, 1.2)):
        brightness = _lit(scene, camera, light).sum(-1)
        unshadowed = _lit(without_pillar, camera, light).sum(-1)
        shadow = slab & (brightness < 0.5 * unshadowed)   # the ground the pillar darkens
        assert shadow.sum() >= 6, shadow.sum()
        shadows.append(shadow)
    west_light, east_light = shadows
    assert not (west_light & east_light).any()
    # the image's x axis points east here: a west light casts the shadow east, an east light west
    assert west_light.nonzero()[1].mean() > 12 > east_light.nonzero()[1].mean()


def test_olat_glossy_highlight_is_sharp_and_moves_with_the_light():
    """A close view of the red sphere (specular 0.7, shininess 40), two lights either side of the
    camera: the highlight (green above what diffuse light gives the red albedo) is a few pixels
    and it moves."""
    scene = olat_scene("olat-glossy")
    red = scene.primitives[1]
    assert red.material.specular >= 0.6 and red.material.shininess >= 40
    centre = np.asarray(red.center)
    out = np.array([-0.4, -0.8, 0.45]) / np.linalg.norm([-0.4, -0.8, 0.45])
    camera = _camera(tuple(centre + 2.0 * out), tuple(centre), 24, 0.4)
    on_sphere = _centre_hits(scene, camera) == 1
    side = np.cross(out, [0.0, 0.0, 1.0])
    centroids = []
    for sign in (-1, 1):
        light = LIGHT_RADIUS * (out + 0.5 * sign * side) / np.linalg.norm(out + 0.5 * sign * side)
        rgb = _lit(scene, camera, tuple(centre + light))
        # diffuse light gives at most 0.12 · (0.2 + 0.8 E) ≈ 0.15 in green (E = I/r² ≈ 1.3 here)
        highlight = on_sphere & (rgb[..., 1] > 0.3)
        assert 1 <= highlight.sum() <= 0.1 * on_sphere.sum(), (highlight.sum(), on_sphere.sum())
        centroids.append(np.argwhere(highlight).mean(0))
    assert math.dist(*centroids) >= 2.0, centroids
