"""Datasets: image I/O, the four readers, validation errors, and the synthetic scene generator."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import meshio
import numpy as np
import OpenImageIO as oiio
import pycolmap
import pytest
import torch

from radfield.core.geometry.cameras import Camera, look_at, opencv_to_opengl
from radfield.errors import RadfieldError
from radfield.datasets import detect_format, load_dataset, read_image, resize_area, validate, write_image
from radfield.demo.scenes import LIGHT, SCENES, orbit_cameras
from radfield.demo.static import generate_scene
from radfield.demo.raytrace import render_view, trace

RED_SPHERE = SCENES["blobs"].primitives[1]  # on top of 'blobs': no other object can hide its centre


def raises_naming(path, fn, *args, match: str = ""):
    """Run fn(*args); it must raise a one-line RadfieldError that names `path` (and `match`)."""
    with pytest.raises(RadfieldError) as info:
        fn(*args)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message, message
    assert match in message, message
    return message


def project(camera: Camera, point) -> tuple[float, float, float]:
    """(u, v, z) of a world point: continuous pixel coordinates and OpenCV depth, written out by hand."""
    x, y, z = (camera.w2c.numpy() @ np.append(point, 1.0))[:3]
    return camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy, z


def write_raw_png(path: Path, pixels: np.ndarray, unassociated: bool = False) -> None:
    """Write integer pixels exactly as given (no conversion by radfield's writer)."""
    spec = oiio.ImageSpec(
        pixels.shape[1], pixels.shape[0], pixels.shape[2], "uint16" if pixels.dtype == np.uint16 else "uint8"
    )
    if unassociated:
        spec.attribute("oiio:UnassociatedAlpha", 1)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(pixels)
    out.close()


def write_transforms(root: Path, frames: list[dict], **meta) -> Path:
    path = root / "transforms.json"
    path.write_text(json.dumps({**meta, "frames": frames}))
    return path


@pytest.fixture(scope="module")
def blobs(tmp_path_factory) -> Path:
    return generate_scene("blobs", tmp_path_factory.mktemp("gen") / "blobs", n_train=8, n_test=3, size=48)


@pytest.fixture
def blobs_copy(blobs, tmp_path) -> Path:
    return Path(shutil.copytree(blobs, tmp_path / "blobs"))


# ---------------------------------------------------------------- synthetic scenes through the reader


def test_generated_layout(blobs):
    assert detect_format(blobs) == "nerf_synthetic"
    for split, count in (("train", 8), ("test", 3)):
        meta = json.loads((blobs / f"transforms_{split}.json").read_text())
        assert len(meta["frames"]) == count
        assert (blobs / split / "r_0.png").is_file() and (blobs / split / "r_0_depth.exr").is_file()
    rgba = read_image(blobs / "train" / "r_0.png")
    assert rgba.shape == (48, 48, 4)
    assert rgba[0, 0, 3] == 0 and (rgba[..., 3] == 1).mean() > 0.1  # transparent background, opaque objects
    mesh = meshio.read(blobs / "mesh.ply")
    assert mesh.cells_dict["triangle"].shape[0] > 100
    scene = json.loads((blobs / "scene.json").read_text())
    assert scene["primitives"][1]["center"] == list(RED_SPHERE.center)
    assert not list(blobs.parent.glob(".blobs.tmp-*"))


@pytest.mark.parametrize("split", ["train", "test"])
def test_synthetic_round_trip_camera_convention(blobs, split):
    """The red sphere's centre, projected by hand with the loaded camera, lands amid red pixels
    (an OpenGL/OpenCV or transpose mistake moves or mirrors it off the sphere)."""
    data = load_dataset(blobs, split, background=(0.0, 0.0, 0.0))
    validate(data)
    rgbs, masks = data.load_images()
    for camera, rgb, mask in zip(data.cameras, rgbs.numpy(), masks.numpy()):
        u, v, z = project(camera, RED_SPHERE.center)
        assert z > 0
        around = (slice(int(v) - 1, int(v) + 2), slice(int(u) - 1, int(u) + 2))  # the sphere is ~9 px wide
        r, g, b = rgb[around].transpose(2, 0, 1)
        assert (mask[around] == 1).all() and (r > 2 * g).all() and (r > 2 * b).all()


def test_synthetic_rerender_matches_files(blobs):
    """Re-rendering with the cameras as loaded reproduces the files up to 8-bit quantisation."""
    data = load_dataset(blobs, "test", background=(0.2, 0.4, 0.6))
    for i, camera in enumerate(data.cameras):
        rgba, depth = render_view(SCENES["blobs"], camera)
        expected = rgba[..., :3] + (1 - rgba[..., 3:]) * np.array([0.2, 0.4, 0.6])
        rgb, mask = data.load_image(i)
        assert np.abs(rgb.numpy() - expected).max() < 2.5 / 255
        assert np.abs(mask.numpy() - rgba[..., 3]).max() < 0.6 / 255
        stored = read_image(blobs / "test" / f"r_{i}_depth.exr")[..., 0]
        assert np.array_equal(stored, depth)
        u, v, z = project(camera, RED_SPHERE.center)
        assert depth[int(v), int(u)] == pytest.approx(z - RED_SPHERE.radius, abs=0.03)


def test_generate_is_deterministic_and_atomic(blobs, tmp_path):
    again = generate_scene("blobs", tmp_path / "again", n_train=8, n_test=3, size=48)
    for name in ("transforms_train.json", "transforms_test.json", "train/r_3.png", "test/r_1.png"):
        assert (again / name).read_bytes() == (blobs / name).read_bytes()
    (tmp_path / "empty").mkdir()
    generate_scene("blobs", tmp_path / "empty", n_train=2, n_test=1, size=16)  # an empty folder is fine
    raises_naming(tmp_path / "again", generate_scene, "blobs", tmp_path / "again", match="not an empty folder")
    with pytest.raises(RadfieldError, match="unknown synthetic scene 'nope'"):
        generate_scene("nope", tmp_path / "nope")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again", "empty"]


def test_workers_render_the_same_scene(tmp_path):
    """Views rendered in worker processes: the same PNGs byte for byte, the same depths (an EXR
    file's bytes hold a time stamp), the same transforms, in view order."""
    one = generate_scene("studio", tmp_path / "one", n_train=3, n_test=2, size=12)
    three = generate_scene("studio", tmp_path / "three", n_train=3, n_test=2, size=12, workers=3)
    files = sorted(p.relative_to(one) for p in one.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(three) for p in three.rglob("*") if p.is_file()) and len(files) > 10
    for name in files:
        if name.suffix == ".exr":
            np.testing.assert_array_equal(read_image(three / name), read_image(one / name))
        else:
            assert (three / name).read_bytes() == (one / name).read_bytes(), name
    with pytest.raises(RadfieldError, match="workers >= 1"):
        generate_scene("blobs", tmp_path / "none", workers=0)


def test_orbit_cameras_distinct_and_seeded():
    train, test = orbit_cameras(40, 8, 64, seed=0)
    centres = torch.stack([c.center for c in train + test])
    assert len(train) == 40 and len(test) == 8
    assert torch.cdist(centres, centres).add(torch.eye(48) * 10).min() > 0.1  # all distinct
    assert (centres[:, 2] > 0).all() and torch.allclose(
        centres.norm(dim=1), torch.full((48,), 4.0, dtype=torch.float64)
    )
    other, _ = orbit_cameras(40, 8, 64, seed=1)
    assert not torch.allclose(train[0].c2w, other[0].c2w)


@pytest.mark.parametrize("name", ["thin", "checker"])
def test_other_scenes(name, tmp_path):
    root = generate_scene(name, tmp_path / name, n_train=3, n_test=1, size=32)
    data = load_dataset(root, "all")
    assert len(data) == 4
    rgb, mask = data.load_images()
    coverage = mask.mean().item()
    assert 0.02 < coverage < 0.6
    points = meshio.read(root / "mesh.ply").points
    assert np.abs(points).max() < 1.0 and np.abs(points).max() > 0.6


def test_glossy_scene_generates_fast_and_its_highlights_move_with_the_view(tmp_path):
    root = generate_scene("glossy", tmp_path / "glossy", n_train=2, n_test=1, size=32)
    assert len(load_dataset(root, "train")) == 2 and len(load_dataset(root, "test")) == 1
    assert SCENES["glossy"].train_views == 100 and SCENES["glossy"].test_views == 20
    # one surface point of the glossy sphere (and of the matte box) seen from two directions
    scene = SCENES["glossy"]
    sphere, box = scene.primitives[1], scene.primitives[3]
    assert sphere.material.specular > 0 and box.material.specular == 0
    for shape, moves in ((sphere, True), (box, False)):
        top = np.asarray(shape.center) + np.array([0.0, 0.0, shape.radius if moves else shape.half_size[2]])
        colours = []
        mirror = 2 * LIGHT[2] * np.array([0.0, 0.0, 1.0]) - np.asarray(LIGHT)  # the light reflected in the normal +z
        for eye in (top + 2 * mirror, top + 2 * np.asarray(LIGHT)):  # at the highlight's peak, then away from it
            d = (top - eye) / np.linalg.norm(top - eye)
            colour, t = trace(scene, eye, (d + np.array([0.0, 0.0, 1e-9]))[None])
            assert np.isclose(t[0], np.linalg.norm(top - eye), atol=1e-3)
            colours.append(colour[0])
        change = np.abs(colours[0] - colours[1]).max()
        assert (change > 0.2) if moves else (change < 1e-6), (shape, colours)


# ---------------------------------------------------------------- image I/O


def test_png_16_bit_and_exr(tmp_path):
    raw = np.array([[[0, 32768, 65535]]], dtype=np.uint16)
    write_raw_png(tmp_path / "a.png", raw)
    assert np.allclose(read_image(tmp_path / "a.png"), raw / 65535.0, atol=1e-7)
    hdr = np.array([[[0.25, 1.5, 10.0]]], dtype=np.float32)
    write_image(tmp_path / "b.exr", hdr)
    assert np.array_equal(read_image(tmp_path / "b.exr"), hdr)  # linear, not clipped
    smooth = np.random.default_rng(0).random((5, 6, 3)).astype(np.float32)
    write_image(tmp_path / "c.png", smooth, bits=16)
    assert np.abs(read_image(tmp_path / "c.png") - smooth).max() <= 0.5 / 65535 + 1e-7
    write_image(tmp_path / "c.png", smooth)  # 8-bit, rounded, replaces the file
    assert np.abs(read_image(tmp_path / "c.png") - smooth).max() <= 0.5 / 255 + 1e-7
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.exr", "c.png"]  # no temporaries left


def test_rgba_composited_and_grey(tmp_path):
    """PNG stores straight alpha: loaded RGB is colour * a + background * (1 - a), mask = a."""
    straight = np.array([[[200, 100, 0, 255], [200, 100, 0, 51], [10, 20, 30, 0]]], dtype=np.uint8)
    write_raw_png(tmp_path / "r_0.png", straight, unassociated=True)
    write_raw_png(tmp_path / "g.png", np.full((1, 3, 1), 128, dtype=np.uint8))
    frame = {"file_path": "r_0", "transform_matrix": np.eye(4).tolist()}
    write_transforms(tmp_path, [frame], fl_x=2.0)
    for background in ((0.0, 0.0, 0.0), (1.0, 0.5, 0.25)):
        rgb, mask = load_dataset(tmp_path, "all", background=background).load_image(0)
        a = straight[..., 3:] / 255.0
        expected = straight[..., :3] / 255.0 * a + np.array(background) * (1 - a)
        assert np.abs(rgb.numpy() - expected).max() < 1e-6
        assert np.allclose(mask.numpy(), a[..., 0])
    grey = read_image(tmp_path / "g.png")
    assert grey.shape == (1, 3, 1)
    image_folder = tmp_path / "photos"
    image_folder.mkdir()
    shutil.copy(tmp_path / "g.png", image_folder / "g.png")
    rgb, mask = load_dataset(image_folder, "all").load_image(0)
    assert rgb.shape == (1, 3, 3) and mask is None and torch.allclose(rgb, torch.tensor(128 / 255))


def test_downscale_matches_area_average_and_camera(blobs):
    full, half = load_dataset(blobs, "train"), load_dataset(blobs, "train", downscale=2)
    rgb_full, _ = full.load_image(1)
    rgb_half, mask_half = half.load_image(1)
    assert rgb_half.shape == (24, 24, 3) and mask_half.shape == (24, 24)
    assert torch.allclose(rgb_half, rgb_full.reshape(24, 2, 24, 2, 3).mean((1, 3)), atol=1e-5)
    c_full, c_half = full.cameras[1], half.cameras[1]
    assert (c_half.width, c_half.fx, c_half.cx) == (24, c_full.fx / 2, c_full.cx / 2)
    odd = resize_area(np.ones((45, 31, 4), dtype=np.float32), 2)
    assert odd.shape == (22, 16, 4) and np.allclose(odd, 1)
    assert c_full.scaled(0.5).width == 24 and Camera(1, 1, 1, 1, 31, 45, torch.eye(4)).scaled(1 / 2).width == 16



def test_the_automatic_factor_is_the_smallest_within_the_size_limit():
    from radfield.datasets.images import downscaled_size, fitting_downscale

    assert fitting_downscale(4032, 3024, 1600) == 3 and fitting_downscale(1700, 1000, 1600) == 2
    assert fitting_downscale(1600, 900, 1600) == 1 and fitting_downscale(1700, 1000, 0) == 1   # 0: no limit
    for width, height, limit in [(3201, 40, 1600), (3203, 40, 1600), (999, 1001, 7), (5, 3, 1)]:
        k = fitting_downscale(width, height, limit)
        assert max(downscaled_size(width, height, k)) <= limit     # the rounded size, as the camera's
        assert k == 1 or max(downscaled_size(width, height, k - 1)) > limit


def test_large_images_are_downscaled_to_data_max_size_unless_the_user_chose(tmp_path):
    """data.downscale null (the default) downscales images larger than data.max_size by the smallest
    factor that fits, with one note; a number, 1 included, is the user's choice and wins."""
    from radfield.datasets.scene import read_dataset, resolve_downscale
    from radfield.pipeline.config import load_config

    big = tmp_path / "big"
    _nerfstudio_scene(big, 3, size=(1700, 1000), fl_x=1500.0, w=1700, h=1000)
    photos = tmp_path / "photos"
    shutil.copytree(big / "images", photos)   # no cameras: the sizes come from the headers
    data, notes = load_config()["data"], []
    assert data["downscale"] is None and data["max_size"] == 1600
    assert resolve_downscale(big, data, notes.append) == 2 and resolve_downscale(photos, data, notes.append) == 2
    assert notes == ["radfield: note: images of 1700x1000 downscaled by 2 to 850x500 (data.max_size 1600; "
                     "--downscale 1 keeps the full size)"] * 2
    notes.clear()
    assert resolve_downscale(big, {**data, "downscale": 1}, notes.append) == 1          # the user's 1 wins
    assert resolve_downscale(big, {**data, "max_size": 0}, notes.append) == 1           # no limit
    assert resolve_downscale(big, {**data, "max_size": 1700}, notes.append) == 1        # within it
    assert notes == []
    assert resolve_downscale(big, {**data, "max_size": 400}, notes.append) == 5 and "to 340x200" in notes[0]
    scene, _ = read_dataset(big, data)
    assert scene["downscale"] == 2 and {(v["width"], v["height"], v["file_width"]) for v in scene["splits"]["train"]} == {(850, 500, 1700)}



def test_a_run_records_the_automatic_factor_and_the_user_s_choice_wins(tmp_path, cli):
    """reconstruct on 1700x1000 images: one note, scene.json and RUN/config.yaml hold the factor 2
    (so later commands and the cache see it: a second run is cached); --downscale 1 keeps the full
    size and says nothing. run_pipeline resolves the automatic factor too (the data stage's resolve)."""
    from radfield.pipeline.config import load_config
    from radfield.pipeline.runner import run_pipeline
    from radfield.stages import data, sfm

    big = tmp_path / "big"
    _nerfstudio_scene(big, 3, size=(1700, 1000), fl_x=1500.0, w=1700, h=1000)

    def sizes(run: Path) -> set:
        scene = json.loads((run / "data" / "scene.json").read_text())
        return {(scene["downscale"], v["width"], v["height"]) for split in scene["splits"].values() for v in split}

    code, out, err = cli("reconstruct", big, "-o", tmp_path / "auto", "--until", "data", "-q")
    assert code == 0, err
    assert [line for line in err.splitlines() if "note" in line] == [
        "radfield: note: images of 1700x1000 downscaled by 2 to 850x500 (data.max_size 1600; --downscale 1 keeps the full size)"]
    assert sizes(tmp_path / "auto") == {(2, 850, 500)}
    assert load_config(tmp_path / "auto" / "config.yaml")["data"]["downscale"] == 2
    code, out, err = cli("reconstruct", big, "-o", tmp_path / "auto", "--until", "data", "-q")
    assert code == 0 and "data cached" in out, err
    for user in (["--downscale", "1"], ["--set", "data.downscale=1"], ["--set", "data.max_size=0"]):
        code, out, err = cli("reconstruct", big, "-o", tmp_path / "full", "--until", "data", "-q", *user)
        assert code == 0 and "note" not in err and sizes(tmp_path / "full") == {(1, 1700, 1000)}, (user, err)
    run_pipeline([sfm.STAGE, data.STAGE], tmp_path / "api", load_config(sets=["stages=[sfm, data]"]), input_path=big,
                 quiet=True)
    assert sizes(tmp_path / "api") == {(2, 850, 500)}
    assert load_config(tmp_path / "api" / "config.yaml")["data"]["downscale"] == 2


# ---------------------------------------------------------------- nerfstudio / instant-ngp


def _nerfstudio_scene(root: Path, n: int, size=(12, 10), **meta) -> list[torch.Tensor]:
    """n images (named so that sorting differs from list order) with OpenCV poses looking at the origin."""
    root.mkdir(exist_ok=True)
    (root / "images").mkdir()
    poses, frames = [], []
    for k in reversed(range(n)):
        c2w = look_at((3 * math.cos(k), 3 * math.sin(k), 1.0), (0, 0, 0))
        poses.insert(0, c2w)
        write_image(root / "images" / f"f{k:02d}.png", np.full((size[1], size[0], 3), k / n, dtype=np.float32))
        frames.append({"file_path": f"images/f{k:02d}.png", "transform_matrix": opencv_to_opengl(c2w).tolist()})
    write_transforms(root, frames, **meta)
    return poses


def test_nerfstudio_reader(tmp_path):
    poses = _nerfstudio_scene(tmp_path, 10, fl_x=11.0, fl_y=12.0, cx=6.5, cy=4.5, w=12, h=10)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    meta["frames"][0].update(fl_x=20.0, cx=5.0)  # per-frame override on f09
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    assert detect_format(tmp_path) == "nerfstudio"
    train, test, every = (load_dataset(tmp_path, s) for s in ("train", "test", "all"))
    assert [v.image_path.name for v in test.views] == ["f00.png", "f08.png"]  # every 8th by file name
    assert len(train) == 8 and len(every) == 10
    for k, camera in enumerate(every.cameras):
        assert torch.allclose(camera.c2w, poses[k])
        assert camera.name == f"f{k:02d}" and (camera.width, camera.height) == (12, 10)
        assert (camera.fx, camera.cx) == ((20.0, 5.0) if k == 9 else (11.0, 6.5)) and camera.fy == 12.0
    assert every.views[0].distortion is None
    assert load_dataset(tmp_path / "transforms.json", "test").image_paths == test.image_paths
    raises_naming(tmp_path / "transforms.json", load_dataset, tmp_path, "val", match="no 'val' split")


def test_nerfstudio_split_lists_and_camera_angle(tmp_path):
    _nerfstudio_scene(
        tmp_path,
        4,
        camera_angle_x=1.0,
        train_filenames=["images/f00.png", "./images/f01.png"],
        val_filenames=["images/f02.png"],
        test_filenames=["images/f03.png"],
    )
    assert [v.image_path.name for v in load_dataset(tmp_path, "val").views] == ["f02.png"]
    assert len(load_dataset(tmp_path, "train")) == 2
    camera = load_dataset(tmp_path, "test").cameras[0]  # no w/h/fl_x: size from the image, fx from the angle
    assert (camera.width, camera.height, camera.cx) == (12, 10, 6.0)
    assert camera.fx == pytest.approx(6 / math.tan(0.5)) and camera.fy == camera.fx


def test_undistortion_marks_its_invalid_border_pixels(tmp_path):
    """The pixels undistortion cannot fill from the file (black) are exactly the ones the valid mask
    leaves out, at full and at half resolution; a view without distortion has no mask."""
    w, h, f = 64, 48, 50.0
    (tmp_path / "images").mkdir()
    write_image(tmp_path / "images" / "a.png", np.ones((h, w, 3), np.float32))
    write_image(tmp_path / "images" / "b.png", np.ones((h, w, 3), np.float32))
    frames = [{"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist(), "k1": 0.4, "k2": 0.1},
              {"file_path": "images/b.png", "transform_matrix": np.eye(4).tolist(), "k1": 0.0}]
    write_transforms(tmp_path, frames, fl_x=f, fl_y=f, w=w, h=h)
    data = load_dataset(tmp_path, "all")
    rgb, _ = data.load_image(0)
    mask = data.load_valid_mask(0)
    assert mask.shape == (h, w) and mask.dtype == torch.bool
    assert 0 < int((~mask).sum()) < 0.5 * h * w and bool(mask[h // 2, w // 2])
    assert not mask[0, 0] and not mask[-1, -1]          # k1 > 0 leaves the corners empty
    assert rgb[mask].min() > 0.999 and rgb[~mask].max(-1).values.max() < 0.999
    assert data.load_valid_mask(1) is None
    masks = data.load_valid_masks()
    assert masks.shape == (2, h, w) and torch.equal(masks[0], mask) and bool(masks[1].all())
    half = load_dataset(tmp_path, "all", downscale=2).load_valid_mask(0)
    blocks = mask.reshape(h // 2, 2, w // 2, 2).all(3).all(1)   # valid only if all four source pixels are
    assert torch.equal(half, blocks)


def test_nerfstudio_undistorts(tmp_path):
    """An image distorted with k1/k2/p1/p2 loads back as the pinhole image it came from."""
    w, h, f = 80, 60, 70.0
    ii, jj = np.mgrid[0:h, 0:w].astype(np.float32)
    pinhole = np.stack([0.5 + 0.4 * np.sin(jj / 2), 0.5 + 0.4 * np.cos(ii / 2), np.full_like(ii, 0.5)], -1)
    coeffs = np.array([0.3, -0.05, 0.002, -0.003])
    # Distorted pixel p shows the pinhole image at undistort(p) (cv2: pixel centres at integers).
    K = np.array([[f, 0, w / 2 - 0.5], [0, f, h / 2 - 0.5], [0, 0, 1]])
    points = np.stack([jj, ii], -1).reshape(-1, 1, 2).astype(np.float64)
    source = cv2.undistortPoints(points, K, coeffs, P=K).reshape(h, w, 2).astype(np.float32)
    distorted = cv2.remap(pinhole, source[..., 0], source[..., 1], cv2.INTER_LINEAR)
    (tmp_path / "images").mkdir()
    write_image(tmp_path / "images" / "a.png", distorted, bits=16)
    frame = {"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}
    write_transforms(tmp_path, [frame], fl_x=f, fl_y=f, w=w, h=h, k1=0.3, k2=-0.05, p1=0.002, p2=-0.003)
    data = load_dataset(tmp_path, "all")
    assert np.allclose(data.views[0].distortion, coeffs)
    rgb, _ = data.load_image(0)
    inner = (slice(10, -10), slice(10, -10))
    assert np.abs(distorted - pinhole)[inner].max() > 0.2
    assert np.abs(rgb.numpy() - pinhole)[inner].max() < 0.03


def test_a_missing_shared_dataset_skips_locally_and_fails_in_ci(shared_dataset, monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    with pytest.raises(pytest.skip.Exception, match="shared dataset not found"):
        shared_dataset("no_such_dataset")
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="must not skip"):
        shared_dataset("no_such_dataset")
    assert shared_dataset("fox_small", "images").name == "fox_small"  # present: a path either way


@pytest.mark.parametrize(
    "name, counts, size, distorted",
    [
        ("fox_small", (43, 7), (225, 400), True),
        ("fern", (17, 3), (504, 378), True),
        ("lego_small", (100, 25), (400, 400), False),
    ],
)
def test_shared_datasets(name, counts, size, distorted, shared_dataset):
    root = shared_dataset(name)
    for split, count in zip(("train", "test"), counts):
        data = load_dataset(root, split)
        validate(data)
        assert len(data) == count
        assert {(c.width, c.height) for c in data.cameras} == {size}
        assert (data.views[0].distortion is not None) == distorted
    rgb, mask = data.load_image(0)
    assert rgb.shape == (size[1], size[0], 3) and (mask is not None) == (name == "lego_small")
    if name == "lego_small":
        assert data.cameras[0].fx == pytest.approx(555.555, abs=0.01)


# ---------------------------------------------------------------- COLMAP


def _colmap_scene(root: Path, model: str = "PINHOLE", text: bool = False) -> tuple[list[Camera], np.ndarray]:
    """A reconstruction written with pycolmap: 9 views of 'blobs' rendered from known cameras, 5 points."""
    train, test = orbit_cameras(6, 3, 32)
    cameras = train + test
    rec = pycolmap.Reconstruction()
    c = cameras[0]
    params = {
        "PINHOLE": [c.fx, c.fy, c.cx, c.cy],
        "SIMPLE_RADIAL": [c.fx, c.cx, c.cy, 0.05],
        "OPENCV_FISHEYE": [c.fx, c.fy, c.cx, c.cy, 0.1, 0, 0, 0],
    }[model]
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(camera_id=1, model=model, width=c.width, height=c.height, params=params)
    )
    (root / "images").mkdir(parents=True)
    for k, camera in enumerate(cameras):
        name = f"v{k}.png"
        write_image(root / "images" / name, render_view(SCENES["blobs"], camera)[0])
        pose = pycolmap.Rigid3d(camera.w2c.numpy()[:3])
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=k + 1), pose)
    xyz = np.random.default_rng(0).uniform(-1, 1, (5, 3))
    for k, p in enumerate(xyz):
        rec.add_point3D(p, pycolmap.Track(), np.array([50 * k, 255, 0], dtype=np.uint8))
    model_dir = root / "sparse" / "0"
    model_dir.mkdir(parents=True)
    if text:
        rec.write_text(model_dir)
    else:
        rec.write(model_dir)
    return cameras, xyz


@pytest.mark.parametrize("text", [False, True])
def test_colmap_reader(tmp_path, text):
    cameras, xyz = _colmap_scene(tmp_path, text=text)
    assert detect_format(tmp_path) == "colmap"
    data = load_dataset(tmp_path, "all", background=(0, 0, 0))
    validate(data)
    assert len(data) == 9 and len(load_dataset(tmp_path, "test")) == 2  # v0, v8
    for camera, expected in zip(data.cameras, cameras):
        assert torch.allclose(camera.c2w, expected.c2w, atol=1e-9) and camera.fx == pytest.approx(expected.fx)
    rgbs, _ = data.load_images()
    for camera, rgb in zip(data.cameras, rgbs.numpy()):
        u, v, _ = project(camera, RED_SPHERE.center)
        r, g, b = rgb[int(v), int(u)]
        assert r > 2 * g and r > 2 * b
    order = data.points.xyz[:, 0].argsort()  # COLMAP keeps points in a hash map
    expected = np.argsort(xyz[:, 0])
    assert torch.allclose(data.points.xyz[order], torch.tensor(xyz[expected], dtype=torch.float32))
    assert torch.allclose(
        data.points.rgb[order], torch.tensor([[50 * k / 255, 1.0, 0.0] for k in expected], dtype=torch.float32)
    )


def test_colmap_radial_is_undistorted_on_load(tmp_path):
    _colmap_scene(tmp_path, model="SIMPLE_RADIAL")
    data = load_dataset(tmp_path, "test")
    assert np.array_equal(data.views[0].distortion, [0.05, 0.0, 0.0, 0.0])
    assert data.load_image(0)[0].shape == (32, 32, 3)


def test_colmap_refuses_fisheye(tmp_path):
    _colmap_scene(tmp_path, model="OPENCV_FISHEYE")
    raises_naming(tmp_path / "sparse" / "0", load_dataset, tmp_path, "train", match="undistort")


# ---------------------------------------------------------------- detection and errors


def test_image_folder(tmp_path):
    (tmp_path / "images").mkdir()
    for k in range(9):
        write_image(tmp_path / "images" / f"{k}.jpg", np.full((8, 10, 3), 0.5, dtype=np.float32))
    assert detect_format(tmp_path) == "images"
    data = load_dataset(tmp_path, "train", downscale=2)
    assert len(data) == 7 and not data.posed  # 0.jpg and 8.jpg are test views
    assert data.load_images()[0].shape == (7, 4, 5, 3)
    raises_naming(tmp_path, lambda: data.cameras, match="sfm")
    write_image(tmp_path / "images" / "5.jpg", np.zeros((9, 10, 3), dtype=np.float32))
    raises_naming(tmp_path / "images" / "5.jpg", validate, data, match="10x9 but 1.jpg is 10x8")
    raises_naming(tmp_path / "images" / "5.jpg", load_dataset(tmp_path, "train").load_images, match="10x9 but 1.jpg")
    (tmp_path / "images" / "5.jpg").unlink()
    raises_naming(tmp_path / "images" / "5.jpg", validate, data, match="not found")


def test_detect_errors(tmp_path):
    raises_naming(tmp_path, detect_format, tmp_path, match="not a dataset")  # empty folder
    raises_naming(tmp_path / "nope", load_dataset, tmp_path / "nope", match="not found")
    with pytest.raises(RadfieldError, match="unknown split"):
        load_dataset(tmp_path, "validation")
    with pytest.raises(RadfieldError, match="downscale"):
        load_dataset(tmp_path, "train", downscale=0)


def test_missing_image(blobs_copy):
    (blobs_copy / "train" / "r_2.png").unlink()
    raises_naming(blobs_copy / "train" / "r_2", load_dataset, blobs_copy, "train", match="frames[2].file_path")
    load_dataset(blobs_copy, "test")  # other splits unaffected


def test_unreadable_and_truncated_images(blobs_copy):
    data = load_dataset(blobs_copy, "train")
    bad = blobs_copy / "train" / "r_1.png"
    bad.write_bytes(b"not an image")
    raises_naming(bad, validate, data)
    raises_naming(bad, data.load_image, 1)
    truncated = blobs_copy / "train" / "r_3.png"
    truncated.write_bytes(truncated.read_bytes()[:200])
    raises_naming(truncated, data.load_image, 3)


def test_size_mismatch(blobs_copy):
    write_image(blobs_copy / "test" / "r_1.png", np.zeros((40, 48, 4), dtype=np.float32))
    data = load_dataset(blobs_copy, "test")
    raises_naming(blobs_copy / "test" / "r_1.png", validate, data, match="48x40 but its camera is 48x48")
    raises_naming(blobs_copy / "test" / "r_1.png", data.load_image, 1)


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda m: "{", "invalid JSON"),
        (lambda m: {k: v for k, v in m.items() if k != "frames"}, "missing key 'frames'"),
        (lambda m: {**m, "camera_angle_x": None}, "missing key 'fl_x' (or 'camera_angle_x')"),
        (lambda m: {**m, "camera_angle_x": "wide"}, "'camera_angle_x' must be a finite number"),
        (lambda m: {**m, "frames": [{"file_path": "./test/r_0"}]}, "frames[0] is missing key 'transform_matrix'"),
        (
            lambda m: {**m, "frames": [{**m["frames"][0], "transform_matrix": [[1, 2]]}]},
            "frames[0].transform_matrix must be a 4x4",
        ),
        (lambda m: {**m, "frames": [{"transform_matrix": np.eye(4).tolist()}]}, "frames[0] is missing key 'file_path'"),
        (lambda m: {**m, "frames": []}, "split 'test' has no images"),
    ],
)
def test_bad_json(blobs_copy, edit, match):
    path = blobs_copy / "transforms_test.json"
    meta = edit(json.loads(path.read_text()))
    path.write_text(meta if isinstance(meta, str) else json.dumps(meta))
    raises_naming(path, load_dataset, blobs_copy, "test", match=match)


def test_a_dataset_with_nothing_visible_is_refused_before_any_stage(blobs_copy, cli, tmp_path):
    """Fully transparent images (alpha 0 everywhere) used to reconstruct with exit 0, a warning
    about the envelope's box fallback and a model of nothing."""
    for png in blobs_copy.rglob("*.png"):
        pixels = (read_image(png) * 255).round().astype(np.uint8)
        pixels[..., 3] = 0
        write_raw_png(png, pixels)
    out = tmp_path / "run"
    code, stdout, err = cli("reconstruct", blobs_copy, "-o", out, "--iterations", "5", "-q")
    assert code == 1 and stdout == ""
    assert err.startswith("radfield: error: ") and err.count("\n") == 1, err
    assert "no object is visible in any view" in err and str(blobs_copy) in err
    assert not out.exists()                                           # nothing written
    # one view with a single visible pixel is enough to go on
    png = blobs_copy / "test" / "r_1.png"
    pixels = (read_image(png) * 255).round().astype(np.uint8)
    pixels[5, 7, 3] = 255
    write_raw_png(png, pixels)
    from radfield.datasets.scene import read_dataset
    from radfield.pipeline.config import load_config
    read_dataset(blobs_copy, load_config()["data"])
