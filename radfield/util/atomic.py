"""The one atomic-write helper of the project: write to a temporary name beside the target, then
rename over it, so a killed process never leaves a half-written file that a later run trusts."""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path


def atomic_write(path: str | Path, write: Callable[[Path], object]) -> Path:
    """Call `write(tmp)` with a temporary path in `path`'s folder, then rename it onto `path`.

    The temporary name keeps `path`'s suffix last (writers such as OpenImageIO, meshio or
    np.savez pick the format from it) and is not made by mkstemp, so the file gets the umask's
    mode. On any failure the temporary file is removed and `path` is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{secrets.token_hex(4)}.tmp{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write `data` to `path` atomically, flushed to disk before the rename."""

    def write(tmp: Path) -> None:
        with open(tmp, "xb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())

    return atomic_write(path, write)


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write `text` (UTF-8) to `path` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


@contextlib.contextmanager
def atomic_folder(path: str | Path, merge: bool = False) -> Iterator[Path]:
    """Yield a new temporary folder beside `path` to fill; when the block ends without error it
    takes `path`'s place, otherwise it is removed and `path` is left as it was. The folder gets the
    umask's mode (mkdtemp's would be private).

    merge=False: `path` must not exist (or be an empty folder): the folder is renamed to it in one
    step. merge=True: into an existing folder each entry of the new one moves by a rename,
    replacing an entry of the same name (renders into a folder the user already has)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    tmp.mkdir()
    try:
        yield tmp
        if merge and path.is_dir() and any(path.iterdir()):
            for entry in sorted(tmp.iterdir()):
                old = path / entry.name
                if old.is_dir() and not old.is_symlink():
                    shutil.rmtree(old)
                elif entry.is_dir() and (old.exists() or old.is_symlink()):
                    old.unlink()
                os.replace(entry, old)
        else:
            if path.is_dir() and not any(path.iterdir()):
                path.rmdir()
            os.rename(tmp, path)   # fails, rather than merging, if `path` appeared meanwhile
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


@contextlib.contextmanager
def new_folder(path: str | Path) -> Iterator[Path]:
    """`atomic_folder` for a folder that must be new: an existing file or non-empty folder at `path`
    is refused (one line) before any work, and `path` ends up complete or absent (the demo scenes)."""
    from radfield.errors import RadfieldError

    path = Path(path)
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise RadfieldError(f"{path}: already exists and is not an empty folder; refusing to overwrite it")
    with atomic_folder(path) as tmp:
        yield tmp
