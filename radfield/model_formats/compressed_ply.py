"""`compressed-ply`: PlayCanvas's compressed PLY (SuperSplat, splat-transform ``.compressed.ply``),
read only.

Splats in chunks of 256. A ``chunk`` element (one row a chunk, float32): ``min_x min_y min_z max_x
max_y max_z min_scale_x .. max_scale_z`` and optionally ``min_r .. max_b``; a ``vertex`` element of
four uint32 a splat: ``packed_position`` and ``packed_scale`` 11-10-11 bit unorms (x in the top 11
bits) between the chunk's bounds (the scales are log σ), ``packed_rotation`` 2 bits for the index of
the quaternion's largest component (w x y z order) and three 10-bit unorms u of the others,
(u − 0.5)·√2, ``packed_color`` 8-8-8-8 bits, r g b = 0.5 + C0·f_dc (between the chunk's colour
bounds when it has them) and a = sigmoid(opacity); an optional ``sh`` element of uchar ``f_rest_i``
(9, 24 or 45, the 3DGS PLY's order), each (n − 0.5)·8 with n = 0 for 0, 1 for 255, (b + 0.5)/256
otherwise. Positions are in the 3DGS PLY's frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from radfield.core.kinds.gaussian import Gaussians
from radfield.core.splat.sh import C0
from radfield.errors import RadfieldError
from radfield.model_formats.base import ModelFormat, checked, gaussians, is_compressed_ply, opacity_logit
from radfield.model_formats.ply_3dgs import REST_COUNTS, read_ply_elements

CHUNK = 256
CHUNK_PROPERTIES = tuple(f"{m}_{a}" for m in ("min", "max") for a in "xyz") + \
    tuple(f"{m}_scale_{a}" for m in ("min", "max") for a in "xyz")
PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")


def _unorm(value: np.ndarray, shift: int, bits: int) -> np.ndarray:
    return ((value >> shift) & ((1 << bits) - 1)).astype(np.float64) / ((1 << bits) - 1)


def _lerp(lo, hi, t):
    return lo * (1 - t) + hi * t


def read_compressed_ply(path: str | Path) -> Gaussians:
    path = Path(path)
    what = "compressed PLY"
    ply = read_ply_elements(path, what)
    names = {e.name for e in ply.elements}
    if not {"chunk", "vertex"} <= names:
        raise RadfieldError(f"{path}: not a {what} (it needs a 'chunk' and a 'vertex' element)")
    chunk, vertex = ply["chunk"], ply["vertex"]
    have_c, have_v = {p.name for p in chunk.properties}, {p.name for p in vertex.properties}
    missing = [n for n in CHUNK_PROPERTIES if n not in have_c] + [n for n in PACKED if n not in have_v]
    if missing:
        raise RadfieldError(f"{path}: not a {what} (missing {', '.join(missing)})")
    n = len(vertex.data)
    if len(chunk.data) != -(-n // CHUNK):
        raise RadfieldError(f"{path}: damaged {what}: {len(chunk.data)} chunks for {n} splats (need {-(-n // CHUNK)})")
    ci = np.arange(n) // CHUNK
    c = lambda name: np.asarray(chunk[name], np.float64)[ci]
    packed = {name: np.asarray(vertex[name]).astype(np.uint32) for name in PACKED}

    def three(value, prefix, suffix=""):
        t = [_unorm(value, 21, 11), _unorm(value, 11, 10), _unorm(value, 0, 11)]
        return np.stack([_lerp(c(f"min_{prefix}{a}"), c(f"max_{prefix}{a}"), t[i]) for i, a in enumerate("xyz")], 1)

    means = three(packed["packed_position"], "")
    log_scales = three(packed["packed_scale"], "scale_")
    rot = packed["packed_rotation"]
    others = np.stack([(_unorm(rot, s, 10) - 0.5) * np.sqrt(2) for s in (20, 10, 0)], 1)
    largest = (rot >> 30).astype(np.int64)
    quats = np.zeros((n, 4))
    slots = np.array([[k for k in range(4) if k != i] for i in range(4)])[largest]   # (P, 3)
    np.put_along_axis(quats, slots, others, 1)
    quats[np.arange(n), largest] = np.sqrt(np.clip(1 - (others ** 2).sum(1), 0, None))
    col = packed["packed_color"]
    rgba = [_unorm(col, s, 8) for s in (24, 16, 8, 0)]
    if {"min_r", "max_r"} <= have_c:
        rgb = np.stack([_lerp(c(f"min_{ch}"), c(f"max_{ch}"), rgba[i]) for i, ch in enumerate("rgb")], 1)
    else:
        rgb = np.stack(rgba[:3], 1)
    dc = (rgb - 0.5) / C0
    rest = np.zeros((n, 0, 3))
    if "sh" in names:
        sh_el = ply["sh"]
        k = len(sh_el.properties)
        if k not in REST_COUNTS or k == 0 or len(sh_el.data) != n:
            raise RadfieldError(f"{path}: damaged {what}: an 'sh' element of {k} properties and {len(sh_el.data)} rows")
        b = np.stack([np.asarray(sh_el[f"f_rest_{i}"], np.float64) for i in range(k)], 1)
        unit = np.where(b == 0, 0.0, np.where(b == 255, 1.0, (b + 0.5) / 256))
        rest = ((unit - 0.5) * 8).reshape(n, 3, k // 3).transpose(0, 2, 1)
    sh = np.concatenate([dc[:, None, :], rest], 1)
    return checked(gaussians(means, log_scales, quats, sh, opacity_logit(rgba[3])), path, what)


FORMAT = ModelFormat(
    name="compressed-ply", suffixes=(".compressed.ply", ".ply"),
    summary="PlayCanvas's compressed PLY (SuperSplat, splat-transform), read only",
    loses="positions and log scales 11-10-11 bits within each 256-splat chunk's bounds, rotations "
          "10 bits a component, colour and opacity 8 bits, SH 8 bits over [-4, 4]",
    read=read_compressed_ply, write=None, exact=False, recognises=is_compressed_ply, priority=10)
