"""Image files through OpenImageIO: list a folder's, read, header-only size check, atomic write,
area downscale. OpenImageIO and cv2 are imported by the functions that touch pixels or headers,
not by this module, so that importing the datasets package (and detecting a dataset) stays cheap.

Alpha convention: arrays with an alpha channel (2 or 4 channels) hold colour *premultiplied* by
alpha, OpenImageIO's convention for every format (EXR stores it that way; PNG stores straight
alpha and OIIO converts on read and write), so compositing on a background is rgb + (1 - a) * bg
and area averaging is exact.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from radfield.util.atomic import atomic_write
from radfield.errors import RadfieldError

if TYPE_CHECKING:
    import OpenImageIO as oiio

# Formats written as 8/16-bit integers (everything else, e.g. EXR, is written as float32).
_INTEGER_FORMATS = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp"}
# Photo formats picked up from a plain folder (OIIO reads them all).
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".webp"}


def list_images(folder: Path) -> list[Path]:
    """Image files directly in `folder`, sorted by name (hidden files skipped)."""
    if not folder.is_dir():
        return []
    return sorted(
        p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and p.is_file()
    )


def _oiio_error(source=None) -> str:
    """The pending error of an ImageInput/ImageOutput (`source`), else OIIO's global one, as one
    line (reading it clears it, so OIIO does not print it at exit)."""
    import OpenImageIO as oiio

    message = source.geterror() if source is not None else ""
    return " ".join((message or oiio.geterror()).split()) or "unknown error"


def _open(path: Path) -> oiio.ImageInput:
    import OpenImageIO as oiio

    if not path.is_file():
        raise RadfieldError(f"image not found: {path}")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise RadfieldError(f"cannot read image {path}: {_oiio_error()}")
    return inp


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Decode an image file (PNG 8/16-bit, JPEG, EXR, anything OIIO reads) to float32 (H, W, C).

    Integer formats map to [0, 1]; EXR values come back as stored (linear, may exceed 1). All
    channels are kept (C = 1 grey, 2 grey+alpha, 3 RGB, 4 RGBA), colour premultiplied by alpha."""
    path = Path(path)
    inp = _open(path)
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if pixels is None or inp.has_error:
            raise RadfieldError(f"cannot decode image {path}: {_oiio_error(inp)}")
    finally:
        inp.close()
    return np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image from its header only (no pixel decode)."""
    path = Path(path)
    inp = _open(path)
    spec = inp.spec()
    inp.close()
    return spec.width, spec.height


def write_image(path: str | os.PathLike, array: np.ndarray, bits: int = 8) -> None:
    """Write float (H, W) or (H, W, C) pixels atomically (util/atomic.py). PNG/JPEG/TIFF are
    quantised to `bits` (8 or 16) with rounding after clipping to [0, 1]; EXR is written as float32. Alpha (C = 2 or 4) is taken as premultiplied, as read_image
    returns it; it is un-premultiplied here in float so that low-alpha pixels keep their colour."""
    import OpenImageIO as oiio

    path = Path(path)
    pixels = np.asarray(array, dtype=np.float32)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    height, width, channels = pixels.shape
    fmt = "float"
    unassociated = False
    if path.suffix.lower() in _INTEGER_FORMATS:
        if bits not in (8, 16):
            raise RadfieldError(f"cannot write {path}: bits must be 8 or 16, not {bits}")
        if channels in (2, 4):
            alpha = pixels[..., -1:]
            colour = np.divide(pixels[..., :-1], alpha, out=np.zeros_like(pixels[..., :-1]), where=alpha > 0)
            pixels, unassociated = np.concatenate([colour, alpha], axis=-1), True
        fmt = "uint8" if bits == 8 else "uint16"
        pixels = np.rint(np.clip(pixels, 0.0, 1.0) * np.iinfo(fmt).max).astype(fmt)
    spec = oiio.ImageSpec(width, height, channels, fmt)
    if unassociated:
        spec.attribute("oiio:UnassociatedAlpha", 1)

    def write(tmp: Path) -> None:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise RadfieldError(f"cannot write image {path}: {_oiio_error()}")
        if not (out.open(str(tmp), spec) and out.write_image(np.ascontiguousarray(pixels))):
            raise RadfieldError(f"cannot write image {path}: {_oiio_error(out)}")
        out.close()

    atomic_write(path, write)


def downscaled_size(width: int, height: int, factor: int) -> tuple[int, int]:
    """Image size after an integer downscale, rounded exactly as `Camera.scaled(1 / factor)`."""
    return max(1, round(width * (1 / factor))), max(1, round(height * (1 / factor)))


def fitting_downscale(width: int, height: int, max_size: int) -> int:
    """The smallest integer factor whose `downscaled_size` has no side longer than `max_size` pixels
    (1 when the image fits; max_size 0: no limit). Tested on the rounded size itself, so the image
    and its camera, which round alike, are within the limit, not just its quotient."""
    if max_size <= 0:
        return 1
    # a side rounds to at most max_size only when its quotient is at most max_size + 1/2: every factor
    # below this one leaves the longest side too long, so the search starts here
    factor = max(1, max(width, height) // (max_size + 1))
    while max(downscaled_size(width, height, factor)) > max_size:
        factor += 1
    return factor


def resize_area(img: np.ndarray, factor: int) -> np.ndarray:
    """Downscale (H, W[, C]) float32 pixels by an integer factor with area averaging (cv2
    INTER_AREA); sizes not divisible by `factor` round like `Camera.scaled`, so image and camera
    stay consistent."""
    if factor == 1:
        return img
    import cv2

    height, width = img.shape[:2]
    out = cv2.resize(img, downscaled_size(width, height, factor), interpolation=cv2.INTER_AREA)
    # cv2 drops a trailing channel axis of size 1.
    return out.reshape(out.shape[:2] + img.shape[2:])
