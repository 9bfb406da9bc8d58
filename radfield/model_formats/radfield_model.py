"""`radfield`: radfield's own model file (safetensors; docs/formats.md "The model file"), every kind
exactly, through radfield.model_file."""

from __future__ import annotations

from pathlib import Path

from radfield.core.kinds.gaussian import Gaussians
from radfield.model_formats.base import ModelFormat, suffix_is


def _read(path: Path):
    from radfield.model_file import load_model

    return load_model(path)


def _write(g: Gaussians, path: Path) -> dict:
    from radfield.model_file import save_model

    save_model(path, g)
    return {"gaussians": len(g), "bytes": Path(path).stat().st_size}


FORMAT = ModelFormat(
    name="radfield", suffixes=(".safetensors",),
    summary="radfield's own model file (every kind)",
    loses="nothing", read=_read, write=_write, exact=True, recognises=suffix_is(".safetensors"))
