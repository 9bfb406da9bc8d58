"""The dataset-format registry (radfield/datasets/formats): detection of each built-in format and
its priority order, the one-line errors for what is not a dataset, the registry's own rules, heavy
libraries left unimported until a format reads, and the seam itself: a format defined in this
file, registered at run time, reconstructed end to end by `radfield reconstruct`."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch

from radfield.core.geometry.cameras import Camera
from radfield.datasets import formats, load_dataset, write_image
from radfield.datasets.formats import DatasetFormat, Reading
from radfield.datasets.scene import load_scene
from radfield.demo.scenes import SCENES, orbit_cameras
from radfield.demo.static import generate_scene
from radfield.demo.raytrace import render_view
from radfield.datasets.views import View
from radfield.errors import RadfieldError
from radfield.pipeline.runner import read_manifest

BUILT_IN = ("nerf_synthetic", "nerfstudio", "colmap", "images")


# ---------------------------------------------------------------- built-in datasets, made small


@pytest.fixture(scope="module")
def nerf_synthetic(tmp_path_factory) -> Path:
    return generate_scene("blobs", tmp_path_factory.mktemp("gen") / "blobs", n_train=3, n_test=2, size=16)


def _frames(root: Path, count: int) -> list[dict]:
    """`count` grey 12x10 PNGs in root/images and their nerfstudio frames (identity poses)."""
    (root / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for k in range(count):
        write_image(root / "images" / f"f{k}.png", np.full((10, 12, 3), k / count, np.float32))
        frames.append({"file_path": f"images/f{k}.png", "transform_matrix": np.eye(4).tolist()})
    return frames


def make_nerfstudio(root: Path) -> Path:
    meta = {"fl_x": 10.0, "w": 12, "h": 10, "frames": _frames(root, 3)}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def make_colmap(root: Path) -> Path:
    """A real (binary) COLMAP model in root/sparse/0 with its images in root/images."""
    _frames(root, 3)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(camera_id=1, model="PINHOLE", width=12, height=10, params=[10.0, 10.0, 6.0, 5.0]))
    for k in range(3):
        pose = pycolmap.Rigid3d(np.hstack([np.eye(3), [[0.0], [0.0], [3.0 + k]]]))
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"f{k}.png", camera_id=1, image_id=k + 1), pose)
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write(root / "sparse" / "0")
    return root


def make_photos(root: Path) -> Path:
    _frames(root, 3)
    return root


# ---------------------------------------------------------------- detection


def test_built_in_formats_in_detection_order():
    assert formats.names() == BUILT_IN
    assert [formats.get(name).name for name in BUILT_IN] == list(BUILT_IN)
    assert [formats.get(name).posed for name in BUILT_IN] == [True, True, True, False]


def test_each_built_in_format_is_detected_and_read(nerf_synthetic, tmp_path):
    cases = {
        "nerf_synthetic": (nerf_synthetic, nerf_synthetic / "transforms_train.json"),
        "nerfstudio": (make_nerfstudio(tmp_path / "ns"), tmp_path / "ns" / "transforms.json"),
        "colmap": (make_colmap(tmp_path / "colmap"), tmp_path / "colmap" / "sparse" / "0"),
    }
    for name, (root, poses) in cases.items():
        fmt = formats.detect(root)
        assert fmt.name == name and fmt.posed
        assert fmt.pose_source(root) == poses
        data = load_dataset(root, "all")
        assert data.format == name and data.posed and len(data) in (3, 5)
    # a transforms.json given as a file is nerfstudio too
    assert formats.detect(tmp_path / "ns" / "transforms.json").name == "nerfstudio"
    # the photos: unposed, found in images/ (or in the folder itself)
    photos = formats.detect(make_photos(tmp_path / "photos"))
    assert photos.name == "images" and not photos.posed
    assert photos.photo_folder(tmp_path / "photos") == tmp_path / "photos" / "images"
    (tmp_path / "loose").mkdir()
    write_image(tmp_path / "loose" / "a.jpg", np.zeros((4, 4, 3), np.float32))
    assert formats.detect(tmp_path / "loose").photo_folder(tmp_path / "loose") == tmp_path / "loose"
    assert not load_dataset(tmp_path / "photos", "all").posed


def test_detection_priority(nerf_synthetic, tmp_path):
    """When a folder matches several formats the earlier one wins: split files over transforms.json
    over a COLMAP model over plain pictures (every posed folder here also holds images/)."""
    both = make_nerfstudio(tmp_path / "both")
    for name in ("transforms_train.json", "transforms_test.json"):
        (both / name).write_text((nerf_synthetic / name).read_text())
    assert formats.detect(both).name == "nerf_synthetic"
    colmap = make_colmap(tmp_path / "colmap")
    assert formats.detect(colmap).name == "colmap"
    (colmap / "transforms.json").write_text((both / "transforms.json").read_text())
    assert formats.detect(colmap).name == "nerfstudio"


def test_what_is_not_a_dataset_gets_the_same_one_line_errors(tmp_path):
    def message(path):
        with pytest.raises(RadfieldError) as info:
            formats.detect(path)
        return str(info.value)

    assert message(tmp_path) == (f"{tmp_path}: not a dataset (no transforms_train.json, transforms.json, "
                                 "sparse/0/cameras.bin|txt or image files)")
    (tmp_path / "notes.txt").write_text("hello")
    assert message(tmp_path / "notes.txt") == (f"{tmp_path / 'notes.txt'}: not a dataset "
                                               "(give a folder or a transforms.json file)")
    assert message(tmp_path / "nope") == f"dataset not found: {tmp_path / 'nope'}"
    with pytest.raises(RadfieldError, match=r"^unknown dataset format 'nope' \(known: nerf_synthetic, nerfstudio, "):
        formats.get("nope")


def test_registry_refuses_a_second_format_of_the_same_name_or_no_name():
    class Again(CamerasJson):
        name = "colmap"

    with pytest.raises(ValueError, match="^dataset format 'colmap' is registered already$"):
        formats.register(Again())
    with pytest.raises(ValueError, match="not a named DatasetFormat"):
        formats.register(type("Nameless", (CamerasJson,), {"name": ""})())
    with pytest.raises(TypeError):  # recognises and read are abstract
        type("Half", (DatasetFormat,), {"name": "half"})()
    assert formats.names() == BUILT_IN


def test_detection_imports_no_heavy_library_and_a_nerf_dataset_loads_without_pycolmap(nerf_synthetic, tmp_path):
    """In a fresh interpreter where `import pycolmap` fails: detecting every built-in format imports
    none of pycolmap, OpenImageIO, cv2 (file names only); a NeRF-synthetic dataset then loads,
    images and all, and the data stage describes it."""
    roots = [nerf_synthetic, make_nerfstudio(tmp_path / "ns"), make_colmap(tmp_path / "colmap"),
             make_photos(tmp_path / "photos")]
    script = textwrap.dedent(f"""
        import sys

        class NoPycolmap:
            def find_spec(self, name, path=None, target=None):
                if name == "pycolmap" or name.startswith("pycolmap."):
                    raise ImportError("pycolmap is not installed here")

        sys.meta_path.insert(0, NoPycolmap())
        from radfield.datasets import formats
        print([formats.detect(root).name for root in {[str(r) for r in roots]!r}])
        print(sorted(m for m in ("pycolmap", "OpenImageIO", "cv2") if m in sys.modules))
        from radfield.datasets import load_dataset
        from radfield.datasets.scene import read_dataset
        rgb, alpha = load_dataset({str(nerf_synthetic)!r}, "train", downscale=2).load_images()
        scene, _ = read_dataset({str(nerf_synthetic)!r},
                                {{"downscale": 1, "background": [1, 1, 1], "test_every": 8, "val_every": 0}})
        print(tuple(rgb.shape), scene["format"], "pycolmap" in sys.modules)
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines == [str(list(BUILT_IN)), "[]", "(3, 8, 8, 3) nerf_synthetic False"]


# ---------------------------------------------------------------- the seam: a format from outside


class CamerasJson(DatasetFormat):
    """A made-up format: `cameras.json` lists pinhole cameras (OpenCV camera-to-world, pixels) with
    their PNG file and split; the PNGs sit beside it."""

    name = "cameras_json"
    priority = 50  # before 'images' (100): its folders hold pictures too
    looks_for = "cameras.json"

    def recognises(self, path: Path) -> bool:
        return (path / "cameras.json").is_file()

    def _entries(self, path: Path) -> list[dict]:
        return json.loads((path / "cameras.json").read_text())["cameras"]

    def read(self, path: Path, split: str) -> Reading:
        views = [View(path / e["file"], Camera(e["fx"], e["fy"], e["cx"], e["cy"], e["width"], e["height"],
                                               torch.tensor(e["c2w"], dtype=torch.float64), Path(e["file"]).stem))
                 for e in self._entries(path) if split in ("all", e["split"])]
        return Reading(views, path / "cameras.json")

    def splits(self, path: Path) -> tuple[str, ...]:
        named = {e["split"] for e in self._entries(path)}
        return tuple(s for s in ("train", "val", "test") if s in named)

    def pose_source(self, path: Path) -> Path:
        return path / "cameras.json"


@pytest.fixture
def cameras_json():
    fmt = formats.register(CamerasJson())
    yield fmt
    formats.unregister(fmt.name)


@pytest.fixture(scope="module")
def cameras_json_dataset(tmp_path_factory) -> Path:
    """6 train and 2 test views of the 'blobs' scene, 24x24 PNGs, described by cameras.json."""
    root = tmp_path_factory.mktemp("plugin") / "scene"
    root.mkdir()
    train, test = orbit_cameras(6, 2, 24)
    entries = []
    for k, (camera, split) in enumerate([(c, "train") for c in train] + [(c, "test") for c in test]):
        write_image(root / f"view{k}.png", render_view(SCENES["blobs"], camera)[0])
        entries.append({"file": f"view{k}.png", "split": split, "fx": camera.fx, "fy": camera.fy, "cx": camera.cx,
                        "cy": camera.cy, "width": camera.width, "height": camera.height,
                        "c2w": camera.c2w.tolist()})
    (root / "cameras.json").write_text(json.dumps({"cameras": entries}))
    return root


def test_a_registered_format_is_detected_before_the_photos_and_named_in_errors(cameras_json, cameras_json_dataset,
                                                                              tmp_path):
    assert formats.names() == ("nerf_synthetic", "nerfstudio", "colmap", "cameras_json", "images")
    assert formats.detect(cameras_json_dataset) is cameras_json
    data = load_dataset(cameras_json_dataset, "test")
    assert data.format == "cameras_json" and len(data) == 2 and data.cameras[0].width == 24
    with pytest.raises(RadfieldError, match=r"sparse/0/cameras\.bin\|txt, cameras\.json or image files\)$"):
        formats.detect(tmp_path)


def test_formats_unregistered_are_forgotten(cameras_json_dataset):
    assert "cameras_json" not in formats.names()
    assert formats.detect(cameras_json_dataset).name == "images"  # only pictures, as far as radfield knows


def test_reconstruct_a_dataset_of_a_format_defined_outside_radfield(cameras_json, cameras_json_dataset, tmp_path,
                                                                  cli):
    """`radfield reconstruct` of the made-up format: detected, read with its own splits, trained,
    evaluated, with no project module changed."""
    run = tmp_path / "run"
    code, out, err = cli("reconstruct", cameras_json_dataset, "-o", run, "-q", "--no-cage",
                         "--set", "train.iterations=30", "--set", "init.num_points=150")
    assert code == 0, err
    assert "poses come from " + str(cameras_json_dataset / "cameras.json") in read_manifest(run / "sfm")["reason"]
    scene = load_scene(run / "data" / "scene.json")
    assert scene.format == "cameras_json" and scene.posed
    assert [len(scene.views(s)) for s in ("train", "test")] == [6, 2]
    expected = json.loads((cameras_json_dataset / "cameras.json").read_text())["cameras"]
    assert [Path(v["image"]).name for v in scene.views("test")] == [e["file"] for e in expected[6:]]
    assert torch.allclose(scene.test_cameras[0].c2w, torch.tensor(expected[6]["c2w"], dtype=torch.float64))
    assert (run / "train" / "model.safetensors").is_file()
    figures = read_manifest(run / "eval")["figures"]
    assert figures["views"] == 2 and np.isfinite(figures["psnr"]) and figures["psnr"] > 10
