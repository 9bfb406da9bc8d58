"""Entry points: detect a dataset's format, load one split of it, validate its images cheaply.

Formats: 'nerf_synthetic' (transforms_{train,val,test}.json), 'nerfstudio' (transforms.json,
also instant-ngp), 'colmap' (sparse/0 + images/), 'images' (unposed photos in the folder or in
its images/ subfolder, for the SfM stage).
"""

from __future__ import annotations

import math
from pathlib import Path

from radfield.errors import RadfieldError
from radfield.datasets.colmap import find_model, read_colmap
from radfield.datasets.images import image_size
from radfield.datasets.transforms import read_nerf_synthetic, read_nerfstudio
from radfield.datasets.views import FORMATS, SPLITS, Dataset, Points, View, llff_split

__all__ = ["Dataset", "Points", "View", "FORMATS", "SPLITS", "detect_format", "load_dataset", "validate", "list_images",
           "photo_folder", "pose_source"]

# Photo formats picked up from a plain folder (OIIO reads them all).
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".webp"}


def list_images(folder: Path) -> list[Path]:
    """Image files directly in `folder`, sorted by name (hidden files skipped)."""
    if not folder.is_dir():
        return []
    return sorted(
        p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and p.is_file()
    )


def photo_folder(path: Path) -> Path:
    """Where the photos of an unposed dataset are: its images/ subfolder when that holds any, else itself."""
    return path / "images" if list_images(path / "images") else path


def pose_source(path: Path, fmt: str) -> Path:
    """The file (or COLMAP model folder) the poses of a posed dataset come from."""
    if fmt == "nerf_synthetic":
        return next(path / f"transforms_{s}.json" for s in ("train", "val", "test")
                    if (path / f"transforms_{s}.json").is_file())
    if fmt == "nerfstudio":
        return path if path.is_file() else path / "transforms.json"
    if fmt == "colmap":
        return find_model(path)
    raise ValueError(f"{fmt} datasets have no poses")


def detect_format(path: str | Path) -> str:
    """One of FORMATS for a dataset folder (or a transforms.json file); RadfieldError otherwise."""
    path = Path(path)
    if not path.exists():
        raise RadfieldError(f"dataset not found: {path}")
    if path.is_file():
        if path.suffix.lower() == ".json":
            return "nerfstudio"
        raise RadfieldError(f"{path}: not a dataset (give a folder or a transforms.json file)")
    if any((path / f"transforms_{s}.json").is_file() for s in ("train", "val", "test")):
        return "nerf_synthetic"
    if (path / "transforms.json").is_file():
        return "nerfstudio"
    if find_model(path) is not None:
        return "colmap"
    if list_images(path / "images") or list_images(path):
        return "images"
    raise RadfieldError(
        f"{path}: not a dataset (no transforms_train.json, transforms.json, sparse/0/cameras.bin|txt or image files)"
    )


def load_dataset(
    path: str | Path, split: str = "train", downscale: int = 1, background: tuple[float, float, float] = (1.0, 1.0, 1.0)
) -> Dataset:
    """One split ('train' | 'val' | 'test' | 'all') of the dataset at `path`, images downscaled by
    an integer factor (area average; cameras scaled to match), RGBA composited on `background`.
    Checks JSON keys and that image files exist; `validate` checks their headers."""
    path = Path(path)
    if split not in SPLITS:
        raise RadfieldError(f"unknown split {split!r} (expected one of {', '.join(SPLITS)})")
    if isinstance(downscale, bool) or not isinstance(downscale, int) or downscale < 1:
        raise RadfieldError(f"downscale must be a positive integer, not {downscale!r}")
    background = tuple(float(c) for c in background)
    if len(background) != 3 or not all(math.isfinite(c) for c in background):
        raise RadfieldError(f"background must be 3 finite numbers, not {background!r}")
    fmt = detect_format(path)
    points = None
    if fmt == "nerf_synthetic":
        views = read_nerf_synthetic(path, split)
        source = path if split == "all" else path / f"transforms_{split}.json"
    elif fmt == "nerfstudio":
        source = path if path.is_file() else path / "transforms.json"
        views = read_nerfstudio(source, split)
    elif fmt == "colmap":
        (views, points), source = read_colmap(path, split), find_model(path)
    else:
        source = photo_folder(path)
        views = [View(p, None) for p in llff_split(list_images(source), split, source)]
    if not views:
        raise RadfieldError(f"{source}: split '{split}' has no images")
    root = path.parent if path.is_file() else path
    return Dataset(root, fmt, split, tuple(views), downscale, background, points)


def validate(dataset: Dataset) -> None:
    """Check every image from its header only (exists, readable, size matches its camera, or the
    first image for unposed photos); the first problem raises a one-line RadfieldError naming the file."""
    expected = None
    for view in dataset.views:
        size = image_size(view.image_path)
        if view.camera is not None:
            expected, what = (view.camera.width, view.camera.height), "its camera is"
        elif expected is None:
            expected, what = size, ""
        else:
            what = f"{dataset.views[0].image_path.name} is"
        if size != expected:
            raise RadfieldError(
                f"{view.image_path}: image is {size[0]}x{size[1]} but {what} {expected[0]}x{expected[1]}"
            )
