"""A dataset described once, for every later stage: the scene.json and points.npz the data stage
writes (RUN/data/), read back as a Scene (cameras, splits, normalisation; images load lazily).

``scene.json``::

    {"version": 1, "format": "nerf_synthetic" | "nerfstudio" | "colmap" | "images" (a datasets/formats name),
     "root": "/abs/dataset", "posed": true, "downscale": 1, "background": [r, g, b],
     "normalization": {"center": [x, y, z], "scale": k} | null,   # null until posed
     "extent": e | null,
     "splits": {"train": [VIEW, ...], "test": [VIEW, ...], "val": [...] (when the dataset has one)}}

    VIEW = {"name", "image": "/abs/file", "fx", "fy", "cx", "cy", "width", "height",
            "c2w": 4x4 list, "file_width", "file_height", "distortion": [k1, k2, p1, p2(, k3)] | null,
            and each condition the view carries (radfield/conditions: "time": ξ_t in [0, 1], a dynamic
            dataset's; "light": {"position" | "direction": [x, y, z], "intensity": k}, a one-light-
            at-a-time capture's, world frame)}

Cameras are OpenCV (x right, y down, z forward) camera-to-world in the dataset's own world frame
(for photos: the sfm stage's output, a COLMAP dataset in its normalised frame, is the dataset);
intrinsics and width/height are at the downscaled resolution (file_width/file_height and
distortion describe the file, so images reload exactly as the readers load them); "downscale" is
the factor applied, data.downscale or the automatic one (resolve_downscale). Unposed photos
(format "images") have "posed": false and views with only name, image, width, height,
file_width, file_height: the sfm stage poses them.

Normalisation (used internally by training; every artifact stays in the world frame):
x_norm = (x − center) · scale. `center` is the median of the SfM points when there are any
(robust to stray points), else the point closest to all the train cameras' optical axes when they
converge (object-centric captures: the middle of the object, where the mean of the camera centres
would sit above it for a hemisphere of views), else the mean of the train camera centres.
`scale` puts every train camera within radius 1 of the centre. `extent` = 1.1 × that radius, in
world units (3DGS's camera extent; 1.1 in normalised units). A view's conditions move with it as
each says (`Condition.normalized`: a point light moves with the cameras, its intensity times scale²).

Splits: the dataset's own (NeRF-synthetic split files, nerfstudio *_filenames lists), else every
`data.test_every`-th view by file name is a test view (the LLFF protocol). With `data.val_every`
N > 0 (and no val split of the dataset's own) every N-th training view becomes a "val" view,
left out of training: tuning and selection look at val, never at test.

``points.npz``: `xyz`, `rgb` (P×3 float32, world frame; SfM points, empty when the dataset has
none) and `mesh_vertices`, `mesh_rgb`, `mesh_faces` (the dataset's `mesh.ply`: vertices, their
colours in [0, 1] and triangles (F×3 int64); empty when there is no mesh, `mesh_rgb` also when the
mesh has no colours, `mesh_faces` when it is a point cloud).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from radfield import conditions
from radfield.core.geometry.cameras import Camera
from radfield.errors import RadfieldError
from radfield.datasets import formats
from radfield.datasets.bounds import MESH, focus_point, read_mesh
from radfield.datasets.images import downscaled_size, fitting_downscale, image_size
from radfield.datasets.readers import SPLITS, Dataset, View, check_visible, load_dataset, validate
from radfield import run as layout

SCENE = layout.SCENE_FILE
POINTS = "points.npz"
FORMAT_VERSION = 1


# --- describing a dataset -----------------------------------------------------------------------


def read_dataset(path: Path, data: dict[str, Any]) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The scene.json content and points.npz arrays of the dataset at `path` under the `data`
    config section. Reads every image header: any problem is a RadfieldError naming the file."""
    path = Path(path).resolve()
    background = tuple(data["background"])
    splits = _splits(path, resolve_downscale(path, data), background, data["test_every"], data["val_every"])
    for dataset in splits.values():
        validate(dataset)
    check_visible(splits.values(), path)
    train = splits["train"]
    points = _points(train)
    scene = {
        "version": FORMAT_VERSION,
        "format": train.format,
        "root": str(train.root),
        "posed": train.posed,
        "downscale": train.downscale,
        "background": list(background),
        "normalization": None,
        "extent": None,
        "splits": {name: [_view_json(d, view) for view in d.views] for name, d in splits.items()},
    }
    if train.posed:
        center, radius = _normalization(train.cameras, points["xyz"])
        scene["normalization"] = {"center": center.tolist(), "scale": 1.0 / radius}
        scene["extent"] = 1.1 * radius
    return scene, points


def resolve_downscale(path: Path, data: dict[str, Any], note=None) -> int:
    """The downscale factor of the dataset at `path` under the `data` config section: data.downscale
    when it is a number (the user's choice, even 1), else (null: automatic) the smallest factor that
    brings the dataset's largest image within data.max_size pixels, 1 when it fits (max_size 0: no
    limit). Photos larger than training needs would otherwise cost their full size in memory and
    time at every step (nerfstudio caps them at 1600 px too); the factor is announced in one note
    line, given to `note` (default: stderr), so that the smaller images surprise no one."""
    if data["downscale"] is not None:
        return data["downscale"]
    if not data["max_size"]:
        return 1
    width, height = max(_image_sizes(Path(path)), key=max)
    factor = fitting_downscale(width, height, data["max_size"])
    if factor > 1:
        small = downscaled_size(width, height, factor)
        (note or _stderr)(f"radfield: note: images of {width}x{height} downscaled by {factor} to {small[0]}x{small[1]} "
                          f"(data.max_size {data['max_size']}; --downscale 1 keeps the full size)")
    return factor


def _image_sizes(path: Path) -> list[tuple[int, int]]:
    """(width, height) of every image of the dataset: its cameras', or the headers' of photos without one."""
    return [(view.camera.width, view.camera.height) if view.camera is not None else image_size(view.image_path)
            for view in load_dataset(path, "all").views]


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _splits(path: Path, downscale: int, background: tuple, test_every: int, val_every: int = 0) -> dict[str, Dataset]:
    """{"train", "test"[, "val"]: Dataset}: the dataset's own split when it has one, else every
    `test_every`-th view (sorted by file name) held out for testing. Then, when val_every > 0 and
    the dataset has no val split of its own, every val_every-th training view (the N-th, 2N-th, ...)
    leaves train for a validation split: what tuning and model selection may look at."""
    native = _native_splits(path)
    if native:
        splits = {split: load_dataset(path, split, downscale, background) for split in native}
    else:
        everything = load_dataset(path, "all", downscale, background)
        views = everything.views
        if len(views) < 2:
            raise RadfieldError(f"{path}: {len(views)} image; a reconstruction needs at least 2 (train and test)")
        train = tuple(view for k, view in enumerate(views) if k % test_every)
        splits = {"train": replace(everything, split="train", views=train),
                  "test": replace(everything, split="test", views=views[::test_every])}
    if val_every > 0 and "val" not in splits:
        train = splits["train"]
        held = {k for k in range(len(train.views)) if (k + 1) % val_every == 0}
        if len(held) == len(train.views) or not held:
            raise RadfieldError(f"data.val_every={val_every} leaves no training or no validation view "
                                f"({len(train.views)} training views)")
        splits["train"] = replace(train, views=tuple(v for k, v in enumerate(train.views) if k not in held))
        splits["val"] = replace(train, split="val", views=tuple(v for k, v in enumerate(train.views) if k in held))
    return splits


def load_split(path: Path, split: str, data: dict[str, Any]) -> Dataset:
    """One split ('train' | 'val' | 'test' | 'all') of the dataset at `path`, as a run with the
    `data` config section sees it (what `radfield render` uses): a split the dataset defines
    itself (a transforms_SPLIT.json, nerfstudio's SPLIT_filenames) is read as it is; otherwise
    every `data.test_every`-th view by file name is the test split and the rest train, as the data
    stage splits it; with data.val_every > 0, val is carved out of train likewise. Images are
    downscaled by data.downscale (resolve_downscale: null is automatic) and composited on data.background."""
    path = Path(path).resolve()
    if split not in SPLITS:
        raise RadfieldError(f"unknown split {split!r} (expected one of {', '.join(SPLITS)})")
    downscale, background = resolve_downscale(path, data), tuple(data["background"])
    present = formats.detect(path).splits(path)
    carved = data["val_every"] > 0 and "val" not in present and split in ("train", "val")  # val cut from train
    if split == "all" or (split in present and not carved):
        return load_dataset(path, split, downscale, background)
    splits = _splits(path, downscale, background, data["test_every"], data["val_every"])
    if split not in splits:
        raise RadfieldError(f"{path}: the dataset has no {split!r} split (it has {', '.join(splits)}; "
                            "data.val_every > 0 makes a val split of the training views)")
    return splits[split]


def _native_splits(path: Path) -> tuple[str, ...]:
    """The splits the dataset defines itself (empty when it defines no train/test split)."""
    present = formats.detect(path).splits(path)
    return present if {"train", "test"} <= set(present) else ()


def _view_json(dataset: Dataset, view: View) -> dict[str, Any]:
    if view.camera is None:
        file_width, file_height = image_size(view.image_path)
        width, height = downscaled_size(file_width, file_height, dataset.downscale)
        return {"name": view.image_path.stem, "image": str(view.image_path), "width": width, "height": height,
                "file_width": file_width, "file_height": file_height}
    cam = view.camera.scaled(1 / dataset.downscale)
    return {
        "name": cam.name or view.image_path.stem,
        "image": str(view.image_path),
        "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
        "width": cam.width, "height": cam.height,
        "c2w": cam.c2w.tolist(),
        "file_width": view.camera.width, "file_height": view.camera.height,
        "distortion": None if view.distortion is None else [float(k) for k in view.distortion],
        # only the conditions the view has, so a static scene's scene.json stays as it was
        **conditions.view_json(cam.conditions),
    }


def _points(train: Dataset) -> dict[str, np.ndarray]:
    """SfM points of the dataset (the readers load them with every split) and its mesh's vertices."""
    empty = np.zeros((0, 3), np.float32)
    xyz, rgb = (empty, empty) if train.points is None else (train.points.xyz.numpy(), train.points.rgb.numpy())
    mesh = read_mesh(train.root / MESH) if (train.root / MESH).is_file() else {
        "mesh_vertices": empty, "mesh_rgb": empty, "mesh_faces": np.zeros((0, 3), np.int64)}
    return {"xyz": xyz.astype(np.float32), "rgb": rgb.astype(np.float32), **mesh}


def _normalization(cameras: list[Camera], points: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre and the radius of the train cameras around it (see the module docstring)."""
    centres = np.stack([cam.center.numpy() for cam in cameras])
    if len(points):
        center = np.median(points.astype(np.float64), axis=0)
    else:
        focus = focus_point(cameras)
        center = centres.mean(axis=0) if focus is None else focus
    radius = float(np.linalg.norm(centres - center, axis=1).max())
    return center, radius if radius > 1e-9 else 1.0  # a single camera position: keep world units


# --- reading scene.json back --------------------------------------------------------------------


class Normalization(NamedTuple):
    """x_norm = (x − center) · scale; `center` (3,) float64 in world units."""

    center: torch.Tensor
    scale: float

    def apply(self, xyz: torch.Tensor) -> torch.Tensor:
        """World points (..., 3) -> normalised frame."""
        return (xyz - self.center.to(xyz)) * self.scale

    def invert(self, xyz: torch.Tensor) -> torch.Tensor:
        """Normalised points (..., 3) -> world frame."""
        return xyz / self.scale + self.center.to(xyz)

    def camera(self, camera: Camera) -> Camera:
        """The same view in the normalised frame (rotation and intrinsics unchanged), its conditions
        moved with it (`Condition.normalized`: a point light moves with the cameras)."""
        c2w = camera.c2w.clone()
        c2w[:3, 3] = self.apply(c2w[:3, 3])
        moved = {name: conditions.get(name).normalized(value, self) for name, value in camera.conditions.items()}
        return replace(camera, c2w=c2w, conditions=moved)


@dataclass(frozen=True)
class Scene:
    """What scene.json describes; images load lazily through the dataset readers."""

    path: Path
    format: str
    root: Path
    posed: bool
    downscale: int
    background: tuple[float, float, float]
    normalization: Normalization | None
    extent: float | None  # world units
    splits: dict[str, list[dict[str, Any]]]

    def views(self, split: str) -> list[dict[str, Any]]:
        if split not in self.splits:
            raise RadfieldError(f"{self.root}: the dataset has no {split!r} split (it has {', '.join(self.splits)})")
        return self.splits[split]

    def values(self, condition: str, split: str) -> list:
        """Each view's value of `condition` (None where it has none), in the split's order, world frame."""
        read = conditions.get(condition).from_json
        return [read(view[condition]) if condition in view else None for view in self.views(split)]

    def cameras(self, split: str) -> list[Camera]:
        if not self.posed:
            raise RadfieldError(f"{self.root}: the photos have no camera poses (the sfm stage poses them)")
        return [_camera(view) for view in self.views(split)]

    def dataset(self, split: str) -> Dataset:
        """The readers' Dataset of a split (loads images one by one: `load_image(i)`)."""
        views = tuple(_dataset_view(view) for view in self.views(split))
        return Dataset(self.root, self.format, split, views, self.downscale, self.background)

    def load_images(self, split: str) -> tuple[torch.Tensor, torch.Tensor | None]:
        """RGB (N, H, W, 3) float32 composited on the background, and alpha (N, H, W) or None."""
        return self.dataset(split).load_images()

    @property
    def train_cameras(self) -> list[Camera]:
        return self.cameras("train")

    @property
    def test_cameras(self) -> list[Camera]:
        return self.cameras("test")

    def valid_masks(self, split: str) -> torch.Tensor | None:
        """Valid pixels (N, H, W) bool of a split's undistorted images, or None when no view has
        lens distortion (every pixel valid): training and evaluation measure these pixels only."""
        return self.dataset(split).load_valid_masks()

    def train_images(self) -> torch.Tensor:
        return self.load_images("train")[0]

    def test_images(self) -> torch.Tensor:
        return self.load_images("test")[0]


def load_scene(path: Path) -> Scene:
    """Read a scene.json written by the data stage."""
    path = Path(path)
    try:
        scene = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise RadfieldError(f"{path}: cannot read scene description ({error})") from None
    if not isinstance(scene, dict) or scene.get("version") != FORMAT_VERSION:
        raise RadfieldError(f"{path}: not a version {FORMAT_VERSION} scene description")
    return scene_from_json(scene, path)


def scene_from_json(scene: dict[str, Any], path: Path) -> Scene:
    """A Scene from scene.json content (`path`: where it came from, for messages)."""
    norm = scene["normalization"]
    return Scene(
        path=Path(path),
        format=scene["format"],
        root=Path(scene["root"]),
        posed=scene["posed"],
        downscale=scene["downscale"],
        background=tuple(scene["background"]),
        normalization=None if norm is None else Normalization(
            torch.tensor(norm["center"], dtype=torch.float64), float(norm["scale"])),
        extent=scene["extent"],
        splits=scene["splits"],
    )


def _camera(view: dict[str, Any]) -> Camera:
    return Camera(view["fx"], view["fy"], view["cx"], view["cy"], view["width"], view["height"],
                  torch.tensor(view["c2w"], dtype=torch.float64), view["name"], conditions.view_values(view))


def _dataset_view(view: dict[str, Any]) -> View:
    """The readers' View (camera at the file's resolution) of a scene.json VIEW."""
    if "c2w" not in view:
        return View(Path(view["image"]), None)
    sx, sy = view["file_width"] / view["width"], view["file_height"] / view["height"]
    camera = Camera(view["fx"] * sx, view["fy"] * sy, view["cx"] * sx, view["cy"] * sy,
                    view["file_width"], view["file_height"], torch.tensor(view["c2w"], dtype=torch.float64),
                    view["name"], conditions.view_values(view))
    distortion = None if view["distortion"] is None else np.asarray(view["distortion"], dtype=np.float64)
    return View(Path(view["image"]), camera, distortion)
