"""nerfstudio / instant-ngp datasets: one `transforms.json` (the folder holding it, or the file
itself). Its splits come from `{train,val,test}_filenames` lists when the file has them, else every
8th frame by file name is 'test'. The file syntax is shared with NeRF-synthetic
(datasets/transforms.py), frames' times and lights included.
"""

from __future__ import annotations

import os
from pathlib import Path

from radfield.errors import RadfieldError
from radfield.datasets.formats.base import DatasetFormat, Reading, llff_split
from radfield.datasets.transforms import check_views, file_path, placed_views, read_json
from radfield.datasets.views import View

_SPLIT_KEYS = {"train": "train_filenames", "val": "val_filenames", "test": "test_filenames"}


def transforms_file(path: Path) -> Path:
    """The transforms.json of a dataset given as its folder or as the file itself."""
    return path if path.is_file() else path / "transforms.json"


def read_nerfstudio(path: Path, split: str) -> list[View]:
    """Views of a nerfstudio / instant-ngp `transforms.json`, sorted by file name. The split comes
    from `{train,val,test}_filenames` when the file has them, else every 8th frame is 'test';
    'all' is every frame."""
    meta = read_json(path)
    frames = sorted(enumerate(meta["frames"]), key=lambda item: file_path(item[1], item[0], path))
    if split == "all" or not any(key in meta for key in _SPLIT_KEYS.values()):
        return _views(meta, llff_split(frames, split, path), path)
    key = _SPLIT_KEYS[split]
    names = meta.get(key, [])
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise RadfieldError(f"{path}: '{key}' must be a list of file names")
    wanted = {os.path.normpath(n) for n in names}
    return _views(meta, [(i, f) for i, f in frames if os.path.normpath(file_path(f, i, path)) in wanted], path)


def _views(meta: dict, frames: list[tuple[int, dict]], path: Path) -> list[View]:
    """The frames' views; their conditions checked together (e.g. point lights against the object's bounds)."""
    placed = placed_views(meta, frames, path)
    check_views(placed, path.parent)
    return [view for *_, view in placed]


class Nerfstudio(DatasetFormat):
    name = "nerfstudio"
    priority = 20
    looks_for = "transforms.json"
    file_kind = "a transforms.json file"

    def recognises(self, path: Path) -> bool:
        # any JSON file given directly is taken as a transforms.json (its name may differ)
        if path.is_file():
            return path.suffix.lower() == ".json"
        return (path / "transforms.json").is_file()

    def read(self, path: Path, split: str) -> Reading:
        source = transforms_file(path)
        return Reading(read_nerfstudio(source, split), source)

    def splits(self, path: Path) -> tuple[str, ...]:
        meta = read_json(transforms_file(path))
        return tuple(s for s in ("train", "val", "test") if _SPLIT_KEYS[s] in meta)

    def pose_source(self, path: Path) -> Path:
        return transforms_file(path)


FORMAT = Nerfstudio()
