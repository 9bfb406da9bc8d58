"""What a dataset format is: how to recognise a folder (or file) as one, and how to read one split
of it to posed views (camera + image file), optionally with SfM points.

A format is a `DatasetFormat` subclass instance in its own module under radfield/datasets/formats/,
registered with `radfield.datasets.formats.register`. Everything format-independent (argument
checks, the Dataset it becomes, validation, the run's splits and normalisation) lives in
datasets/readers.py and datasets/scene.py and asks the registry.

A format module imports its heavy libraries (pycolmap, OpenImageIO, …) inside the functions that
read, never at module level: registering a format, and detecting one, must stay cheap and work on
a machine that lacks the libraries of the formats it does not read.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

from radfield.errors import RadfieldError

if TYPE_CHECKING:
    from radfield.datasets.views import Points, View

# The usual LLFF/NeRF protocol for datasets without split information.
TEST_EVERY = 8


class Reading(NamedTuple):
    """One split as a format read it: its views (sorted as the format orders them), the file or
    folder the split came from (named when the split is empty), and the SfM points or None."""

    views: list[View]
    source: Path
    points: Points | None = None


class DatasetFormat(ABC):
    """A dataset format. Subclasses set the class attributes and implement `recognises` and `read`.

    `name` is what scene.json records as "format" (so it must never change once written).
    `priority` orders detection, lowest first, ties by registration order: the built-in formats
    use 10 (nerf_synthetic), 20 (nerfstudio), 30 (colmap) and 100 (images, which takes any folder
    holding pictures, so a format whose folders also hold pictures needs a priority below 100).
    `looks_for` says what `recognises` looks for, for the "not a dataset (no …)" message;
    `file_kind` names the single file that is a dataset of this format ("a transforms.json file"),
    or None when only folders are. `posed` is False for photos the sfm stage has to pose."""

    name: str = ""
    priority: int = 50
    looks_for: str = ""
    file_kind: str | None = None
    posed: bool = True

    @abstractmethod
    def recognises(self, path: Path) -> bool:
        """Whether the existing folder (or file) `path` is a dataset of this format. Looks at file
        names only (no parsing, no heavy imports): detection runs on every command."""

    @abstractmethod
    def read(self, path: Path, split: str) -> Reading:
        """One split ('train' | 'val' | 'test' | 'all') of the dataset at `path`. Checks what the
        format's own files say (keys, image files exist) and raises a one-line RadfieldError
        naming the file; image headers are checked later (readers.validate)."""

    def splits(self, path: Path) -> tuple[str, ...]:
        """The splits (of train, val, test) the dataset's own files name; () when the format has
        no split information (then every TEST_EVERY-th view by file name is a test view)."""
        return ()

    def pose_source(self, path: Path) -> Path:
        """The file or folder the poses of a posed dataset come from (for messages)."""
        return path

    def photo_folder(self, path: Path) -> Path:
        """Where the photos of an unposed dataset are, for the sfm stage."""
        return path

    def __repr__(self) -> str:
        return f"<dataset format {self.name!r}>"


def llff_split(items: list, split: str, source: Path) -> list:
    """Split `items` (already sorted by file name) by the LLFF/NeRF protocol: every 8th is a test
    view, the rest train; 'all' keeps everything. Such datasets have no validation views."""
    if split == "val":
        raise RadfieldError(
            f"{source}: no 'val' split (no split information: every {TEST_EVERY}th view is 'test', the rest 'train')"
        )
    if split == "all":
        return list(items)
    return [item for k, item in enumerate(items) if (k % TEST_EVERY == 0) == (split == "test")]
