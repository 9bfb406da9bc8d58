"""`ply-3dgs`: the 3D-Gaussian PLY of the Inria 3DGS code, which every 3DGS tool reads and writes.

One binary little-endian vertex element, float32: ``x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity
scale_0..2 rot_0..3``; opacity a logit, log σ scales, w x y z quaternion, ``f_rest`` channel-major
(all R coefficients of bands 1-3, then G, then B). Written exactly (zeros past the model's degree).

Read: any SH degree 0-3 by the ``f_rest`` count (0, 9, 24 or 45), with or without normals, any
other extra property ignored (gsplat, nerfstudio's ``ns-export gaussian-splat``, OpenSplat and
SuperSplat write such variants), any numeric property type (converted to float32). A file that
plyfile cannot parse, lacks a property, has another ``f_rest`` count, or holds a non-finite or
out-of-range number is refused in one line. A PLY with the official Splat the Net MLP
(``frequencies_*``, ``phases_*``, ``amplitudes_*``, ``offsets``) is format ``stn-ply`` (stn_ply.py),
neither recognised nor read here.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from radfield.core.kinds.gaussian import Gaussians
from radfield.core.splat.sh import num_sh_coeffs
from radfield.errors import RadfieldError
from radfield.model_formats.base import ModelFormat, checked, cpu, gaussians, is_compressed_ply, is_stn_names, is_stn_ply
from radfield.util.atomic import atomic_write_bytes

REST_COEFFS = num_sh_coeffs(3) - 1  # 15 per channel: the 45 f_rest of a degree-3 3DGS PLY
REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3")
REST_COUNTS = {0: 0, 9: 1, 24: 2, 45: 3}   # f_rest count -> SH degree


def gaussian_ply_arrays(g: Gaussians) -> dict[str, np.ndarray]:
    """The 3DGS PLY's vertex properties, name -> (P,) float32, in the file's order."""
    import torch

    n = len(g)
    sh = cpu(g.sh)                                             # (P, K, 3)
    rest = np.zeros((n, 3, REST_COEFFS), np.float32)
    rest[:, :, : sh.shape[1] - 1] = sh[:, 1:, :].transpose(0, 2, 1)   # channel-major as the 3DGS code
    quats = torch.nn.functional.normalize(g.quats.detach().to("cpu", torch.float64), dim=-1).float().numpy()
    means, log_scales = cpu(g.means), cpu(g.log_scales)
    columns = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2]}
    columns.update({name: np.zeros(n, np.float32) for name in ("nx", "ny", "nz")})
    columns.update({f"f_dc_{c}": sh[:, 0, c] for c in range(3)})
    columns.update({f"f_rest_{i}": col for i, col in enumerate(rest.reshape(n, -1).T)})
    columns["opacity"] = cpu(g.opacities)
    columns.update({f"scale_{i}": log_scales[:, i] for i in range(3)})
    columns.update({f"rot_{i}": quats[:, i] for i in range(4)})
    return columns


def ply_bytes(elements) -> bytes:
    """A binary little-endian PLY of plyfile elements."""
    from plyfile import PlyData

    buffer = io.BytesIO()
    PlyData(elements, text=False, byte_order="<").write(buffer)
    return buffer.getvalue()


def vertex_element(columns: dict[str, np.ndarray], name: str = "vertex"):
    """A plyfile element of (P,) columns, in their order and dtypes."""
    from plyfile import PlyElement

    first = next(iter(columns.values()))
    table = np.empty(len(first), dtype=[(key, col.dtype.str) for key, col in columns.items()])
    for key, col in columns.items():
        table[key] = col
    return PlyElement.describe(table, name)


def gaussian_ply_bytes(g: Gaussians) -> bytes:
    return ply_bytes([vertex_element(gaussian_ply_arrays(g))])


def read_ply_elements(path: Path, what: str):
    """plyfile's PlyData of `path`, or one error line."""
    from plyfile import PlyData, PlyParseError

    try:
        return PlyData.read(str(path))
    except FileNotFoundError:
        raise RadfieldError(f"{path}: no such file") from None
    except (OSError, ValueError, KeyError, IndexError, EOFError, UnicodeDecodeError, PlyParseError) as error:
        raise RadfieldError(f"{path}: not a readable {what} ({str(error).splitlines()[0] if str(error) else type(error).__name__})") from None


def read_gaussian_ply(path: str | Path) -> Gaussians:
    """A 3DGS PLY (any SH degree 0-3, the variants of the module docstring) as Gaussians."""
    path = Path(path)
    ply = read_ply_elements(path, "3DGS PLY")
    names = [e.name for e in ply.elements]
    if "vertex" not in names:
        raise RadfieldError(f"{path}: not a 3DGS PLY (no 'vertex' element; elements: {', '.join(names) or 'none'})")
    v = ply["vertex"]
    have = {p.name for p in v.properties}
    if is_stn_names(have):   # its own format: drawn as Gaussians it would be another model
        raise RadfieldError(f"{path}: a Splat the Net PLY (frequencies_*, phases_*, amplitudes_*, offsets), "
                            "not a 3DGS PLY: read it as format stn-ply")
    missing = [name for name in REQUIRED if name not in have]
    if missing:
        raise RadfieldError(f"{path}: not a 3DGS PLY (the vertex element lacks {', '.join(missing)})")
    n_rest = sum(name.startswith("f_rest_") for name in have)
    if n_rest not in REST_COUNTS or any(f"f_rest_{i}" not in have for i in range(n_rest)):
        raise RadfieldError(f"{path}: a 3DGS PLY has 0, 9, 24 or 45 f_rest properties (f_rest_0 ...), "
                            f"this one {n_rest}")
    try:
        col = lambda *keys: np.stack([np.asarray(v[k], np.float64) for k in keys], 1) if keys else np.zeros((len(v.data), 0))
        rest = col(*(f"f_rest_{i}" for i in range(n_rest))).reshape(len(v.data), 3, n_rest // 3).transpose(0, 2, 1)
        sh = np.concatenate([col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :], rest], 1)
        with np.errstate(over="ignore", invalid="ignore"):
            g = gaussians(col("x", "y", "z"), col("scale_0", "scale_1", "scale_2"),
                          col("rot_0", "rot_1", "rot_2", "rot_3"), sh, col("opacity")[:, 0])
    except (ValueError, TypeError) as error:
        raise RadfieldError(f"{path}: not a readable 3DGS PLY ({error})") from None
    return checked(g, path, "3DGS PLY")


def write_gaussian_ply(g: Gaussians, path: Path) -> dict:
    data = gaussian_ply_bytes(g)
    atomic_write_bytes(path, data)
    return {"gaussians": len(g), "bytes": len(data)}


def _is_plain_ply(path: Path) -> bool:
    return path.name.lower().endswith(".ply") and not is_compressed_ply(path) and not is_stn_ply(path)


FORMAT = ModelFormat(
    name="ply-3dgs", suffixes=(".ply",),
    summary="the Inria 3DGS PLY, read by every 3DGS tool",
    loses="nothing: every number float32 as the model holds it (the quaternion normalised)",
    read=read_gaussian_ply, write=write_gaussian_ply, exact=True, recognises=_is_plain_ply, priority=60)
