"""What a loaded dataset is: posed views (camera + image file), one split of them, and the
pixels they load to (float32 torch tensors, RGBA composited on a background)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import torch

from radfield.core.geometry.cameras import Camera
from radfield.errors import RadfieldError
from radfield.datasets.images import read_image, resize_area

SPLITS = ("train", "val", "test", "all")


@dataclass(frozen=True, eq=False)
class View:
    """One image file and its camera at the file's resolution.

    `distortion` holds OpenCV lens coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]) of the file,
    or None; loading undistorts the pixels to the pinhole `camera` (same intrinsics matrix), so
    every camera downstream is a plain pinhole. `camera` is None for unposed photos (format
    'images', which the SfM stage poses)."""

    image_path: Path
    camera: Camera | None
    distortion: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Points:
    """A sparse point cloud from SfM: xyz (P, 3) float32 world positions, rgb (P, 3) float32 in [0, 1]."""

    xyz: torch.Tensor
    rgb: torch.Tensor

    def __len__(self) -> int:
        return self.xyz.shape[0]


def undistort(img: np.ndarray, camera: Camera, coeffs: np.ndarray) -> np.ndarray:
    """Remove OpenCV lens distortion from (H, W, C) pixels, keeping the intrinsics matrix (pixels
    that map outside the source come out 0: black, or transparent with alpha)."""
    import cv2

    K = camera.K.numpy().copy()
    # cv2 puts pixel centres at integer coordinates, Camera at +0.5.
    K[:2, 2] -= 0.5
    return cv2.undistort(img, K, coeffs).reshape(img.shape)


# a pixel is valid when at least this fraction of its interpolation weight came from inside the file
_VALID_WEIGHT = 1.0 - 1e-3
_valid_cache: dict[tuple, np.ndarray] = {}


def valid_pixels(camera: Camera, coeffs: np.ndarray, downscale: int = 1) -> np.ndarray:
    """(H, W) bool at 1/downscale resolution: the pixels that undistortion fills from inside the
    file. The others (the borders a barrel or pincushion lens leaves) come out black and are no
    image content. Computed by undistorting an all-ones image the same way as the pixels: a pixel
    is valid when its value is ≥ 1 − 1e-3 (bilinear taps all inside), and after an area downscale
    when every pixel it averages is valid. Cached per camera intrinsics, coefficients and factor."""
    key = (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
           np.asarray(coeffs, np.float64).tobytes(), downscale)
    if key not in _valid_cache:
        ones = np.ones((camera.height, camera.width, 1), np.float32)
        valid = (undistort(ones, camera, coeffs) >= _VALID_WEIGHT).astype(np.float32)
        _valid_cache[key] = resize_area(valid, downscale)[..., 0] >= _VALID_WEIGHT
    return _valid_cache[key]


def split_alpha(img: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(H, W, C) pixels -> RGB (H, W, 3) and alpha (H, W) or None; grey is repeated to RGB."""
    channels = img.shape[2]
    alpha = img[..., -1] if channels in (2, 4) else None
    colour = np.repeat(img[..., :1], 3, axis=-1) if channels <= 2 else img[..., :3]
    return colour, alpha


@dataclass(frozen=True, eq=False)
class Dataset:
    """One split of a dataset: its views, how they load, and the SfM points when the format has them.

    `cameras[i]` matches `load_image(i)`: the file's camera scaled by 1/downscale."""

    root: Path
    format: str
    split: str
    views: tuple[View, ...]
    downscale: int = 1
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    points: Points | None = None

    def __len__(self) -> int:
        return len(self.views)

    @property
    def posed(self) -> bool:
        return all(view.camera is not None for view in self.views)

    @property
    def image_paths(self) -> list[Path]:
        return [view.image_path for view in self.views]

    @property
    def names(self) -> list[str]:
        """Each view's frame name: its image file's name without the extension."""
        return [view.image_path.stem for view in self.views]

    def view_index(self, which: str, option: str = "--camera") -> int:
        """The index of the view `which` names: its frame name, else its index in the split."""
        names = self.names
        if which in names:
            return names.index(which)
        if which.isdigit() and int(which) < len(names):
            return int(which)
        shown = ", ".join(names[:6]) + (", ..." if len(names) > 6 else "")
        raise RadfieldError(f"{option} {which!r}: no view of that name (or index) in the {self.split} split ({shown}; "
                            f"indices 0 to {len(names) - 1})")

    @cached_property
    def cameras(self) -> list[Camera]:
        if not self.posed:
            raise RadfieldError(f"{self.root}: the images have no camera poses yet (run the sfm stage first)")
        return [view.camera.scaled(1 / self.downscale) for view in self.views]

    def load_image(self, i: int) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Pixels of view i: RGB (H, W, 3) float32 composited on the background, and the alpha
        mask (H, W) float32 in [0, 1], or None when the file has no alpha."""
        view = self.views[i]
        img = read_image(view.image_path)
        camera = view.camera
        if camera is not None:
            height, width = img.shape[:2]
            if (width, height) != (camera.width, camera.height):
                raise RadfieldError(
                    f"{view.image_path}: image is {width}x{height} but its camera is {camera.width}x{camera.height}"
                )
            if view.distortion is not None:
                img = undistort(img, camera, view.distortion)
        rgb, alpha = split_alpha(resize_area(img, self.downscale))
        if alpha is not None:
            # Colour is premultiplied (see images.py), so this is the "over" operator.
            rgb = rgb + (1.0 - alpha[..., None]) * np.asarray(self.background, dtype=np.float32)
        return torch.from_numpy(np.ascontiguousarray(rgb)), None if alpha is None else torch.from_numpy(alpha.copy())

    def load_valid_mask(self, i: int) -> torch.Tensor | None:
        """The valid pixels (H, W) bool of view i after undistortion (`valid_pixels`), or None
        when the view has no lens distortion (every pixel valid)."""
        view = self.views[i]
        if view.distortion is None or view.camera is None:
            return None
        return torch.from_numpy(valid_pixels(view.camera, view.distortion, self.downscale).copy())

    def load_valid_masks(self) -> torch.Tensor | None:
        """Valid pixels of every view (N, H, W) bool (all true for views without distortion), or
        None when no view has distortion."""
        masks = [self.load_valid_mask(i) for i in range(len(self))]
        if all(mask is None for mask in masks):
            return None
        shape = next(mask.shape for mask in masks if mask is not None)
        return torch.stack([torch.ones(shape, dtype=torch.bool) if m is None else m for m in masks])

    def load_images(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        """All views at once: RGB (N, H, W, 3) and masks (N, H, W) (1 for views without alpha),
        or None when no file has alpha. Needs every view at the same size."""
        loaded = [self.load_image(i) for i in range(len(self))]
        if not loaded:
            raise RadfieldError(f"{self.root}: split '{self.split}' has no images")
        (height, width, _), first = loaded[0][0].shape, self.views[0].image_path.name
        for view, (rgb, _) in zip(self.views, loaded):
            if rgb.shape[:2] != (height, width):
                raise RadfieldError(
                    f"{view.image_path}: image is {rgb.shape[1]}x{rgb.shape[0]} but {first} is {width}x{height}"
                )
        rgbs = torch.stack([rgb for rgb, _ in loaded])
        if all(mask is None for _, mask in loaded):
            return rgbs, None
        return rgbs, torch.stack([torch.ones(height, width) if mask is None else mask for _, mask in loaded])
