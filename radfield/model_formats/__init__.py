"""The model-format registry: the one place that knows which model file formats radfield reads and
writes, as radfield.datasets.formats does for datasets. A format is one module here that defines a
`ModelFormat` (model_formats/base.py) as its `FORMAT`; a new format is a new module plus its name
in the tuple at the end (or a `register` call from anywhere: a plugin, a test).

    register(fmt)      add a format (its name must be new)
    unregister(name)   remove one
    get(name)          the format of that name
    names()            every format's name, in detection order
    writable()         the names of those radfield writes
    detect(path)       the first format, in priority order, that recognises `path`
    read(path)         detect(path).read(path): the model in the file
    load(path, device) read(path) on `device`: what the commands that take a model file call, so
                       that each takes a file of any format read here (a radfield model file is
                       read by radfield.model_file.load_model, exactly)
    write(name, gaussians, path)   write 3D Gaussians as format `name`; figures for the report

Formats: `radfield` (the model file, every kind), `ply-3dgs` (the Inria 3DGS PLY), `compressed-ply`
(PlayCanvas's, read only), `splat` (antimatter15), `spz` (Niantic, versions 2-3), `glb` (glTF 2.0 with
KHR_gaussian_splatting), `stn-ply` (the official Splat the Net PLY, read only, as neural
primitives). Each module's docstring gives its byte layout and what it loses (docs/formats.md,
"Exports" and "Model formats read").
"""

from __future__ import annotations

from pathlib import Path

from radfield.errors import RadfieldError
from radfield.model_formats import compressed_ply, glb, ply_3dgs, radfield_model, splat, spz, stn_ply
from radfield.model_formats.base import ModelFormat
from radfield.util.registry import Registry

__all__ = ["ModelFormat", "detect", "get", "load", "names", "read", "register", "unregister", "writable", "write"]

_REGISTRY: Registry[ModelFormat] = Registry("model format", order=lambda fmt: fmt.priority)


def register(fmt: ModelFormat) -> ModelFormat:
    """Add `fmt` and return it; ValueError when its name is empty or taken."""
    if not isinstance(fmt, ModelFormat) or not fmt.name:
        raise ValueError(f"{fmt!r} is not a named ModelFormat")
    return _REGISTRY.register(fmt.name, fmt)


def unregister(name: str) -> None:
    _REGISTRY.unregister(name)


def names() -> tuple[str, ...]:
    return _REGISTRY.names()


def writable() -> tuple[str, ...]:
    """The formats radfield writes 3D Gaussians in."""
    return tuple(fmt.name for fmt in _REGISTRY.values() if fmt.write is not None)


def get(name: str) -> ModelFormat:
    return _REGISTRY.get(name)


def detect(path: str | Path) -> ModelFormat:
    """The format of the model file at `path`; one error line when it is missing or none claims it."""
    path = Path(path)
    if not path.is_file():
        raise RadfieldError(f"{path}: no such model file")
    for fmt in _REGISTRY.values():
        if fmt.recognises(path):
            return fmt
    suffixes = sorted({s for fmt in _REGISTRY.values() for s in fmt.suffixes})
    raise RadfieldError(f"{path}: not a model file radfield reads (suffixes: {', '.join(suffixes)})")


def read(path: str | Path, format: str | None = None):
    """The model in `path` (Gaussians for the 3DGS formats), by `format` or detected."""
    fmt = get(format) if format else detect(path)
    return fmt.read(Path(path))


def load(path: str | Path, device="cpu"):
    """The model in the file at `path`, whatever its format (detected), on `device`."""
    return read(path).to(device)


def write(name: str, gaussians, path: str | Path) -> dict:
    """Write `gaussians` (radfield.core.kinds.gaussian.Gaussians) as format `name` to `path`."""
    fmt = get(name)
    if fmt.write is None:
        raise RadfieldError(f"radfield reads {name} but does not write it (written: {', '.join(writable())})")
    return fmt.write(gaussians, Path(path))


for _module in (radfield_model, compressed_ply, stn_ply, ply_3dgs, splat, spz, glb):
    register(_module.FORMAT)
