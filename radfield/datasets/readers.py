"""Entry points that hold for every format: detect a dataset's format, load one split of it,
validate its images cheaply. What each format looks like and how it is read is in
datasets/formats/ (one module per format, found through the registry there).
"""

from __future__ import annotations

import math
from pathlib import Path

from radfield.errors import RadfieldError
from radfield.datasets import formats
from radfield.datasets.images import image_size, read_image
from radfield.datasets.views import SPLITS, Dataset, Points, View

__all__ = ["Dataset", "Points", "View", "SPLITS", "check_visible", "detect_format", "load_dataset", "validate"]


def detect_format(path: str | Path) -> str:
    """The name of the format of the dataset folder (or transforms.json file) at `path`
    (formats.detect); RadfieldError otherwise."""
    return formats.detect(path).name


def load_dataset(
    path: str | Path, split: str = "train", downscale: int = 1, background: tuple[float, float, float] = (1.0, 1.0, 1.0)
) -> Dataset:
    """One split ('train' | 'val' | 'test' | 'all') of the dataset at `path`, images downscaled by
    an integer factor (area average; cameras scaled to match), RGBA composited on `background`.
    Checks the format's files and that image files exist; `validate` checks their headers."""
    path = Path(path)
    if split not in SPLITS:
        raise RadfieldError(f"unknown split {split!r} (expected one of {', '.join(SPLITS)})")
    if isinstance(downscale, bool) or not isinstance(downscale, int) or downscale < 1:
        raise RadfieldError(f"downscale must be a positive integer, not {downscale!r}")
    background = tuple(float(c) for c in background)
    if len(background) != 3 or not all(math.isfinite(c) for c in background):
        raise RadfieldError(f"background must be 3 finite numbers, not {background!r}")
    fmt = formats.detect(path)
    views, source, points = fmt.read(path, split)
    if not views:
        raise RadfieldError(f"{source}: split '{split}' has no images")
    root = path.parent if path.is_file() else path
    return Dataset(root, fmt.name, split, tuple(views), downscale, background, points)


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


def check_visible(datasets, where) -> None:
    """Refuse datasets whose images show nothing: every image has an alpha channel that is 0
    everywhere (such a dataset reconstructed to a model of nothing, with exit 0). Reads pixels only
    until the first image that shows something, so a usual dataset costs one decode (its first
    image): an image without an alpha channel (a photo) shows something.
    `datasets`: Dataset objects (the splits); `where`: the dataset named in the error."""
    for dataset in datasets:
        for view in dataset.views:
            pixels = read_image(view.image_path)
            if pixels.shape[-1] not in (2, 4) or (pixels[..., -1] > 0).any():
                return
    raise RadfieldError(f"{where}: no object is visible in any view (every image's alpha is 0 everywhere)")
