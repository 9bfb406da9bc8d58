"""Unposed photos: image files in the folder or in its images/ subfolder. The sfm stage poses them
(datasets/sfm.py) and the data stage then reads its COLMAP output; read directly, they load without
cameras. Every 8th photo by file name is 'test'. Detection tries this format last: any folder
holding pictures qualifies.
"""

from __future__ import annotations

from pathlib import Path

from radfield.datasets.formats.base import DatasetFormat, Reading, llff_split
from radfield.datasets.images import list_images
from radfield.datasets.views import View


def photo_folder(path: Path) -> Path:
    """Where the photos are: the images/ subfolder when that holds any, else the folder itself."""
    return path / "images" if list_images(path / "images") else path


class Photos(DatasetFormat):
    name = "images"
    priority = 100
    looks_for = "image files"
    posed = False

    def recognises(self, path: Path) -> bool:
        return bool(list_images(path / "images") or list_images(path))

    def read(self, path: Path, split: str) -> Reading:
        source = photo_folder(path)
        return Reading([View(p, None) for p in llff_split(list_images(source), split, source)], source)

    def photo_folder(self, path: Path) -> Path:
        return photo_folder(path)


FORMAT = Photos()
