"""What every model format shares: the `ModelFormat` record the registry holds, the checks every
reader ends with, and the axis conventions of the 3DGS world.

Conventions. A 3DGS PLY holds its numbers in the frame it was trained in, which the 3DGS tools call
RDF (x right, y down, z forward: COLMAP's camera axes); radfield writes its world frame there
unchanged. SPZ stores RUB (Niantic's spec: y and z flipped) and glTF LUF (+y up, +z forward: x and y
flipped), and the tools that convert between them (Niantic's spz library, PlayCanvas splat-transform)
treat a PLY as RDF. Both are half turns (`HALF_TURN_X`, `HALF_TURN_Z`), so a radfield model written
as SPZ or GLB and read back is the same model, and a PLY converted by those tools reads as radfield's
own SPZ or GLB would.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from radfield.core import kinds
from radfield.core.kinds.gaussian import Gaussians
from radfield.core.splat.sh import sh_basis
from radfield.errors import RadfieldError

HALF_TURN_X = (1.0, -1.0, -1.0)   # RDF (a 3DGS PLY) <-> RUB (SPZ)
HALF_TURN_Z = (-1.0, -1.0, 1.0)   # RDF (a 3DGS PLY) <-> LUF (glTF)


@dataclass(frozen=True)
class ModelFormat:
    """One model file format. `read(path)` returns the model (Gaussians for every 3DGS format);
    `write(gaussians, path)` writes 3D Gaussians atomically and returns figures for the report
    ({"gaussians": P, "bytes": N, ...}), None for a format radfield reads only. `exact`: a written
    model reads back equal to float32 precision; otherwise `loses` says what the format quantises.
    `recognises(path)` looks at the suffix (and, where two formats share one, at the first bytes)."""

    name: str
    suffixes: tuple[str, ...]
    summary: str
    loses: str
    read: Callable[[Path], kinds.Primitives]
    write: Callable[[Gaussians, Path], dict] | None
    exact: bool
    recognises: Callable[[Path], bool]
    priority: int = 50      # detection order (lower first): a format that sniffs content before a suffix-only one


def suffix_is(*suffixes: str) -> Callable[[Path], bool]:
    return lambda path: path.name.lower().endswith(suffixes)


def is_compressed_ply(path: Path) -> bool:
    """A PLY whose header declares a ``chunk`` element (or named ``*.compressed.ply``)."""
    if path.name.lower().endswith(".compressed.ply"):
        return True
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    header = head.split(b"end_header", 1)[0]
    return head.startswith(b"ply") and b"\nelement chunk " in header


STN_PREFIXES = ("frequencies_", "phases_", "amplitudes_")   # the official Splat the Net PLY's MLP (stn_ply.py)


def ply_vertex_properties(path: Path, limit: int = 1 << 16) -> list[str]:
    """The property names the header of the PLY at `path` declares for its ``vertex`` element (from
    its first `limit` bytes); [] for a file that is not a PLY or cannot be read."""
    try:
        with open(path, "rb") as f:
            head = f.read(limit)
    except OSError:
        return []
    if not head.startswith(b"ply"):
        return []
    names, in_vertex = [], False
    for line in head.split(b"end_header", 1)[0].splitlines():
        words = line.split()
        if words[:1] == [b"element"]:
            in_vertex = words[1:2] == [b"vertex"]
        elif words[:1] == [b"property"] and in_vertex and len(words) >= 3:
            names.append(words[-1].decode("latin-1"))
    return names


def is_stn_names(names) -> bool:
    """Whether vertex properties `names` are those of an official Splat the Net PLY: any of its MLP's
    (``frequencies_*``, ``phases_*``, ``amplitudes_*``, ``offsets``), which no 3DGS PLY has."""
    return any(name == "offsets" or name.startswith(STN_PREFIXES) for name in names)


def is_stn_ply(path: Path) -> bool:
    """A ``.ply`` whose vertex element declares the official Splat the Net MLP (is_stn_names)."""
    return path.name.lower().endswith(".ply") and not is_compressed_ply(path) and is_stn_names(ply_vertex_properties(path))


def cpu(t: torch.Tensor) -> np.ndarray:
    return t.detach().to("cpu", torch.float32).numpy()


def unit_quats(g: Gaussians) -> np.ndarray:
    """(P, 4) float64 w x y z, normalised."""
    q = g.quats.detach().to("cpu", torch.float64)
    return torch.nn.functional.normalize(q, dim=-1).numpy()


def sh_signs(axes: tuple[float, float, float], degree: int) -> np.ndarray:
    """(K,) the sign each SH basis function (3DGS order) takes under the axis flip diag(`axes`):
    every real SH basis function is even or odd in each coordinate, so Y_k(F d) = sign_k Y_k(d)."""
    d = torch.tensor([[0.31, 0.52, 0.79]], dtype=torch.float64)
    d = d / d.norm()
    ratio = sh_basis(d * torch.tensor(axes, dtype=torch.float64), degree) / sh_basis(d, degree)
    return np.sign(ratio[0].numpy())


def turned(g: Gaussians, axes: tuple[float, float, float]) -> Gaussians:
    """`g` under the half turn diag(`axes`) (two of them −1, a rotation): positions flipped, the
    quaternion's vector part flipped likewise (F R Fᵀ), SH coefficients by their basis' parity.
    Its own inverse."""
    f = torch.tensor(axes, dtype=g.means.dtype)
    quats = g.quats * torch.cat([torch.ones(1, dtype=g.quats.dtype), f.to(g.quats.dtype)])
    signs = torch.from_numpy(sh_signs(axes, g.sh_degree)).to(g.sh.dtype)
    return Gaussians(means=g.means * f, log_scales=g.log_scales, quats=quats, sh=g.sh * signs[None, :, None],
                     opacities=g.opacities)


def opacity_logit(alpha: np.ndarray, floor: float = 1 / 510) -> np.ndarray:
    """Logits of opacities in [0, 1], kept finite: an opacity below `floor` or above 1 − `floor`
    becomes that bound. The default suits 8-bit opacities: a byte of 0 or 255 becomes 1/510 or
    1 − 1/510, which radfield draws as it draws 0 or 1 (α below 1/255 is skipped, above 0.99
    clamped); float opacities keep theirs down to 2⁻²⁴."""
    a = np.clip(np.asarray(alpha, np.float64), floor, 1 - floor)
    return np.log(a / (1 - a)).astype(np.float32)


def checked(g: Gaussians, path: Path, what: str) -> Gaussians:
    """`g` if every number is finite and within the ranges a model file allows (the kind's
    check_values: |log s| ≤ 25, |μ| ≤ 1e12, quaternion norms in [1e-6, 1e6]); else one error line."""
    for name, t in g.tensors().items():
        if not torch.isfinite(t).all():
            row = int(torch.nonzero(~torch.isfinite(t.reshape(len(t), -1)).all(-1))[0])
            raise RadfieldError(f"{path}: damaged {what}: '{name}' is not finite at Gaussian {row}")
    if len(g) == 0:
        raise RadfieldError(f"{path}: the {what} holds no Gaussians")
    bad = kinds.of(g).check_values(g)
    if bad is not None:
        name, row, why = bad
        raise RadfieldError(f"{path}: {what} out of range: '{name}' at Gaussian {row} ({why})")
    return g


def gaussians(means, log_scales, quats, sh, opacities) -> Gaussians:
    """Gaussians of numpy arrays (float32): quats w x y z, sh (P, K, 3)."""
    t = lambda a: torch.from_numpy(np.array(a, dtype=np.float32))   # a copy: the file's buffer may be read-only
    return Gaussians(means=t(means), log_scales=t(log_scales), quats=t(quats), sh=t(sh), opacities=t(opacities))
