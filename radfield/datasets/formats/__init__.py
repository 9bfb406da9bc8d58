"""The dataset-format registry: the one place that knows which formats exist and in what order a
folder is tried against them. A format is one module here (nerf_synthetic, nerfstudio, colmap,
photos) that defines a `DatasetFormat` (formats/base.py) as its `FORMAT`; a new format is a new
module plus its name in the tuple at the end (or a `register` call from anywhere: a plugin, a test).

    register(fmt)     add a format (its name must be new)
    unregister(name)  remove one
    get(name)         the format of that name (what scene.json's "format" records)
    names()           every format's name, in detection order
    detect(path)      the first format, in priority order, that recognises `path`

Registration imports no format's heavy libraries: format modules import them when they read.
"""

from __future__ import annotations

from pathlib import Path

from radfield.datasets.formats import colmap, nerf_synthetic, nerfstudio, photos
from radfield.datasets.formats.base import DatasetFormat, Reading, llff_split
from radfield.errors import RadfieldError
from radfield.util.registry import Registry

__all__ = ["DatasetFormat", "Reading", "detect", "get", "llff_split", "names", "register", "unregister"]

# listed (and tried) in priority order; equal priorities keep their registration order
_REGISTRY: Registry[DatasetFormat] = Registry("dataset format", order=lambda fmt: fmt.priority)


def register(fmt: DatasetFormat) -> DatasetFormat:
    """Add `fmt` to the registry and return it; ValueError when its name is empty or taken."""
    if not isinstance(fmt, DatasetFormat) or not fmt.name:
        raise ValueError(f"{fmt!r} is not a named DatasetFormat")
    return _REGISTRY.register(fmt.name, fmt)


def unregister(name: str) -> None:
    """Remove the format `name` (nothing when there is none)."""
    _REGISTRY.unregister(name)


def names() -> tuple[str, ...]:
    """The registered formats' names in detection order."""
    return _REGISTRY.names()


def get(name: str) -> DatasetFormat:
    """The format called `name`; a one-line RadfieldError when none is (e.g. a scene.json written
    with a format that is not registered in this process)."""
    return _REGISTRY.get(name)


def detect(path: str | Path) -> DatasetFormat:
    """The format of the dataset folder (or file) at `path`: the first, in priority order, that
    recognises it; a one-line RadfieldError saying what was looked for when none does."""
    path = Path(path)
    if not path.exists():
        raise RadfieldError(f"dataset not found: {path}")
    ordered = _REGISTRY.values()
    for fmt in ordered:
        if fmt.recognises(path):
            return fmt
    if path.is_file():
        files = [fmt.file_kind for fmt in ordered if fmt.file_kind]
        raise RadfieldError(f"{path}: not a dataset (give a folder{''.join(f' or {kind}' for kind in files)})")
    looked_for = [fmt.looks_for for fmt in ordered if fmt.looks_for]
    listed = ", ".join(looked_for[:-1]) + " or " + looked_for[-1] if len(looked_for) > 1 else "".join(looked_for)
    raise RadfieldError(f"{path}: not a dataset (no {listed})")


# The built-in formats (detection order comes from their priorities, not from this tuple).
for _module in (nerf_synthetic, nerfstudio, colmap, photos):
    register(_module.FORMAT)
