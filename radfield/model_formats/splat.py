"""`splat`: antimatter15's .splat, the legacy format of web viewers.

32 bytes a splat, little-endian: position 3 × float32, linear σ = exp(log σ) 3 × float32, RGBA
4 × uint8 (0.5 + C0·f_dc and sigmoid(opacity), ×255 truncated, clamped), rotation 4 × uint8
((q/|q|)·128 + 128 truncated, clamped, w x y z), in decreasing order of exp(Σ log σ)·sigmoid(opacity),
as that viewer's convert.py writes it. No header: any file of whole 32-byte records. Read back as the
viewers draw it: colour b/255, opacity a/255, quaternion (b − 128)/128, SH degree 0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from radfield.core.kinds.gaussian import Gaussians
from radfield.core.splat.sh import C0
from radfield.errors import RadfieldError
from radfield.model_formats.base import ModelFormat, checked, cpu, gaussians, opacity_logit, suffix_is
from radfield.util.atomic import atomic_write_bytes

RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])


def splat_bytes(g: Gaussians) -> bytes:
    """antimatter15 .splat records (see the module docstring), most important first."""
    means = cpu(g.means)
    log_scales = cpu(g.log_scales)
    opacity = 1 / (1 + np.exp(-cpu(g.opacities).astype(np.float64)))
    order = np.argsort(-np.exp(log_scales.astype(np.float64).sum(-1)) * opacity, kind="stable")
    rgba = np.concatenate([0.5 + C0 * cpu(g.sh[:, 0, :]), opacity[:, None]], -1)
    quats = cpu(g.quats).astype(np.float64)
    quats = quats / np.linalg.norm(quats, axis=-1, keepdims=True)
    record = np.empty(len(g), dtype=RECORD)
    record["position"] = means
    record["scale"] = np.exp(log_scales)
    record["rgba"] = (rgba * 255).clip(0, 255).astype(np.uint8)
    record["rot"] = (quats * 128 + 128).clip(0, 255).astype(np.uint8)
    return record[order].tobytes()


def read_splat(path: str | Path) -> Gaussians:
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise RadfieldError(f"{path}: cannot read ({error.strerror or error})") from None
    if not data or len(data) % RECORD.itemsize:
        raise RadfieldError(f"{path}: not a .splat file ({len(data)} bytes is not a whole number of 32-byte splats)")
    r = np.frombuffer(data, RECORD)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_scales = np.log(r["scale"].astype(np.float64))
    rgba = r["rgba"].astype(np.float64) / 255
    quats = (r["rot"].astype(np.float64) - 128) / 128
    dc = (rgba[:, :3] - 0.5) / C0
    g = gaussians(r["position"], log_scales, quats, dc[:, None, :], opacity_logit(rgba[:, 3]))
    return checked(g, path, ".splat file")


def write_splat(g: Gaussians, path: Path) -> dict:
    data = splat_bytes(g)
    atomic_write_bytes(path, data)
    return {"gaussians": len(g), "bytes": len(data)}


FORMAT = ModelFormat(
    name="splat", suffixes=(".splat",),
    summary="antimatter15's .splat, for web viewers",
    loses="SH bands 1-3 (view-dependent colour); colour and opacity 8 bits truncated; rotation 8 bits "
          "a component; positions and scales float32",
    read=read_splat, write=write_splat, exact=False, recognises=suffix_is(".splat"))
