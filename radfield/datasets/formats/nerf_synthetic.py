"""NeRF-synthetic (Blender) datasets: `transforms_train.json`, `transforms_val.json`,
`transforms_test.json` beside the image folders they name; one file per split, so the dataset's
splits are the files present. The file syntax is shared with nerfstudio (datasets/transforms.py).

D-NeRF datasets are this layout with a `time` in [0, 1] on every frame (of every split file: the
files are checked together, so a scene is dynamic in all its splits or in none); one-light-at-a-time
captures (and `radfield demo-scene olat`) with a light on every frame, checked the same way.
"""

from __future__ import annotations

from pathlib import Path

from radfield.datasets.formats.base import DatasetFormat, Reading
from radfield.datasets.transforms import check_frames, check_views, placed_views, read_json
from radfield.datasets.views import View

_SPLITS = ("train", "val", "test")


def split_file(root: Path, split: str) -> Path:
    return root / f"transforms_{split}.json"


def read_nerf_synthetic(root: Path, split: str) -> list[View]:
    """Views of `root/transforms_{split}.json` ('all': every split file present)."""
    present = [split_file(root, name) for name in _SPLITS if split_file(root, name).is_file()]
    wanted = present if split == "all" else [split_file(root, split)]
    metas = {path: read_json(path) for path in dict.fromkeys((*present, *wanted))}
    check_frames(list(metas.items()))  # the split files together: times (lights) on every frame or none
    placed = []
    for path in wanted:
        placed += placed_views(metas[path], list(enumerate(metas[path]["frames"])), path)
    check_views(placed, root)
    return [view for *_, view in placed]


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
