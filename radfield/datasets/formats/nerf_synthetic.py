"""NeRF-synthetic (Blender) datasets: `transforms_train.json`, `transforms_val.json`,
`transforms_test.json` beside the image folders they name; one file per split, so the dataset's
splits are the files present. The file syntax is shared with nerfstudio (datasets/transforms.py).
"""

from __future__ import annotations

from pathlib import Path

from radfield.datasets.formats.base import DatasetFormat, Reading
from radfield.datasets.transforms import frame_views, read_json
from radfield.datasets.views import View

_SPLITS = ("train", "val", "test")


def split_file(root: Path, split: str) -> Path:
    return root / f"transforms_{split}.json"


def read_nerf_synthetic(root: Path, split: str) -> list[View]:
    """Views of `root/transforms_{split}.json` ('all': every split file present)."""
    views = []
    for name in _SPLITS if split == "all" else (split,):
        path = split_file(root, name)
        if split == "all" and not path.is_file():
            continue
        meta = read_json(path)
        views += frame_views(meta, list(enumerate(meta["frames"])), path)
    return views


class NerfSynthetic(DatasetFormat):
    name = "nerf_synthetic"
    priority = 10
    looks_for = "transforms_train.json"

    def recognises(self, path: Path) -> bool:
        return any(split_file(path, s).is_file() for s in _SPLITS)

    def read(self, path: Path, split: str) -> Reading:
        return Reading(read_nerf_synthetic(path, split), path if split == "all" else split_file(path, split))

    def splits(self, path: Path) -> tuple[str, ...]:
        return tuple(s for s in _SPLITS if split_file(path, s).is_file())

    def pose_source(self, path: Path) -> Path:
        return next(split_file(path, s) for s in _SPLITS if split_file(path, s).is_file())


FORMAT = NerfSynthetic()
