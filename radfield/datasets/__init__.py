"""Datasets: image I/O, the dataset-format registry and its readers (datasets/formats/:
NeRF-synthetic, nerfstudio, COLMAP, photo folders), and synthetic scenes with exact ground truth.

The names below are re-exported lazily (PEP 562 `__getattr__`): importing one datasets module
(`radfield.datasets.images`, `.scene`, …) does not import the readers and every format with it.
"""

from __future__ import annotations

from importlib import import_module

# name -> the module (under radfield.datasets) that defines it
_EXPORTS = {
    "SPLITS": "views",
    "Dataset": "views",
    "Points": "views",
    "View": "views",
    "detect_format": "readers",
    "load_dataset": "readers",
    "validate": "readers",
    "image_size": "images",
    "list_images": "images",
    "read_image": "images",
    "resize_area": "images",
    "write_image": "images",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_EXPORTS})
