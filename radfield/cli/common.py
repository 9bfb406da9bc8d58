"""Helpers that every command module of the CLI shares: option parsing, device and model
resolution, the progress bar. Raise RadfieldError for user mistakes; main() prints them."""

from __future__ import annotations

import math
from pathlib import Path

from radfield.errors import RadfieldError
from radfield.util.progress import progress_bar

__all__ = ["parse_background", "progress_bar", "resolve_device", "resolve_model"]


def parse_background(text: str) -> tuple[float, float, float]:
    """'R,G,B' with components in [0, 1] (e.g. 1,1,1 for white)."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in values):
        raise RadfieldError(f"--background must be three numbers in [0, 1] like 1,1,1, got {text!r}")
    return values


def resolve_device(name: str):
    import torch

    if name not in ("cpu", "cuda") and not name.startswith("cuda:"):
        raise RadfieldError(f"--device must be cpu or cuda[:N], got {name!r}")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise RadfieldError(f"--device {name}: this torch build sees no CUDA device (use --device cpu)")
    return torch.device(name)


def resolve_model(path: Path) -> Path:
    """A model file, or a run directory whose final model is used."""
    from radfield.pipeline.info import model_path

    if path.is_dir():
        model = model_path(path)
        if not model.is_file():
            raise RadfieldError(f"{path}: run directory has no trained model yet ({model} is missing)")
        return model
    if not path.exists():
        raise RadfieldError(f"{path}: no such model file or run directory")
    return path
