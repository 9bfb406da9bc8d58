"""COLMAP datasets: a sparse model (`sparse/0/{cameras,images,points3D}.{bin,txt}`, also
`sparse/` or the folder itself) beside `images/`, read through pycolmap (imported only when a
model is read). Every 8th registered image by name is 'test'; the model's 3D points come along.

COLMAP cameras already use OpenCV axes and continuous pixel coordinates (the centre of the first
pixel is (0.5, 0.5)), as `Camera` does. Pinhole models load as they are; the radial-tangential
models are mapped to OpenCV coefficients and undistorted on load; fisheye and other models are
refused with a request to undistort first.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from radfield.core.geometry.cameras import Camera
from radfield.errors import RadfieldError
from radfield.datasets.formats.base import DatasetFormat, Reading, llff_split
from radfield.datasets.views import Points, View

if TYPE_CHECKING:
    import pycolmap

# COLMAP parameter layouts: focal lengths, principal point, then OpenCV coefficients in order
# (FULL_OPENCV is OpenCV's rational model, k1 k2 p1 p2 k3 k4 k5 k6).
_MODELS = {
    "SIMPLE_PINHOLE": lambda p: (p[0], p[0], p[1], p[2], []),
    "PINHOLE": lambda p: (p[0], p[1], p[2], p[3], []),
    "SIMPLE_RADIAL": lambda p: (p[0], p[0], p[1], p[2], [p[3], 0.0, 0.0, 0.0]),
    "RADIAL": lambda p: (p[0], p[0], p[1], p[2], [p[3], p[4], 0.0, 0.0]),
    "OPENCV": lambda p: (p[0], p[1], p[2], p[3], p[4:8]),
    "FULL_OPENCV": lambda p: (p[0], p[1], p[2], p[3], p[4:12]),
}


def find_model(root: Path) -> Path | None:
    """The folder holding cameras.{bin,txt}: root/sparse/0, root/sparse or root itself."""
    for folder in (root / "sparse" / "0", root / "sparse", root):
        if (folder / "cameras.bin").is_file() or (folder / "cameras.txt").is_file():
            return folder
    return None


def read_colmap(root: Path, split: str) -> tuple[list[View], Points]:
    """Registered images of the model under `root` (sorted by name; every 8th is 'test') with
    their image files in `root/images`, and the model's 3D points."""
    import pycolmap

    model = find_model(root)
    if model is None:
        raise RadfieldError(f"{root}: no COLMAP model (expected sparse/0/cameras.bin or cameras.txt)")
    try:
        rec = pycolmap.Reconstruction(str(model))
    except Exception as e:  # pycolmap raises plain RuntimeError/ValueError for corrupt files
        raise RadfieldError(f"{model}: cannot read COLMAP model: {' '.join(str(e).split())}") from None
    images = sorted((rec.images[i] for i in rec.reg_image_ids()), key=lambda image: image.name)
    views = [_view(rec, image, root / "images", model) for image in llff_split(images, split, model)]
    return views, _points(rec)


def _view(rec: pycolmap.Reconstruction, image: pycolmap.Image, images_dir: Path, model: Path) -> View:
    cam = rec.cameras[image.camera_id]
    layout = _MODELS.get(cam.model.name)
    if layout is None:
        raise RadfieldError(
            f"{model}: camera {cam.camera_id} uses the {cam.model.name} model; undistort the images to a "
            "pinhole model first (colmap image_undistorter) and load the undistorted folder"
        )
    fx, fy, cx, cy, coeffs = layout(list(cam.params))
    # pycolmap 3.x exposes the pose as a property, 4.x as a method.
    pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    w2c = np.vstack([pose.matrix(), [0.0, 0.0, 0.0, 1.0]])
    camera = Camera(fx, fy, cx, cy, cam.width, cam.height, torch.from_numpy(np.linalg.inv(w2c)), Path(image.name).stem)
    coeffs = np.asarray(coeffs, dtype=np.float64)
    return View(images_dir / image.name, camera, coeffs if coeffs.any() else None)


def _points(rec: pycolmap.Reconstruction) -> Points:
    points = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in points], dtype=np.float32).reshape(-1, 3)
    rgb = np.array([p.color for p in points], dtype=np.float32).reshape(-1, 3) / 255.0
    return Points(torch.from_numpy(xyz), torch.from_numpy(rgb))


class Colmap(DatasetFormat):
    name = "colmap"
    priority = 30
    looks_for = "sparse/0/cameras.bin|txt"

    def recognises(self, path: Path) -> bool:
        return find_model(path) is not None

    def read(self, path: Path, split: str) -> Reading:
        views, points = read_colmap(path, split)
        return Reading(views, find_model(path), points)

    def pose_source(self, path: Path) -> Path:
        return find_model(path)


FORMAT = Colmap()
