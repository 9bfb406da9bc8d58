"""`spz`: Niantic's SPZ (github.com/nianticlabs/spz), versions 2 and 3: a gzip stream of a 16-byte
header and the splats' packed arrays, about a tenth of a 3DGS PLY. Written from the format's
published description (no SPZ library on PyPI is kept: `spz` 0.0.1 is a Rust source archive).

Header, little-endian: magic uint32 0x5053474e ("NGSP"), version uint32 (2 or 3), numPoints uint32,
shDegree uint8 (0-3), fractionalBits uint8, flags uint8 (0x1 antialiased, 0x2 extensions follow the
arrays), reserved uint8 0. Then, array after array (N splats):

- positions N × 3 × 24-bit signed fixed point (little-endian, x y z), value = int / 2^fractionalBits;
- alphas N × uint8 = round(255 · sigmoid(opacity));
- colours N × 3 × uint8 = round(255 · (0.15 · f_dc + 0.5)), clamped;
- scales N × 3 × uint8 = round(16 · (log σ + 10)), clamped;
- rotations: version 3 N × uint32 "smallest three" of the unit quaternion in x y z w order: bits
  30-31 the index of the largest component (made positive), then the three others in order, each
  a sign bit and 9 bits of round(511 · |q_i| · √2), the first in the highest bits; version 2
  N × 3 × uint8 = round(127.5 · (x y z) + 127.5) of the quaternion with w ≥ 0;
- SH N × (3, 8 or 15 coefficients) × 3 channels × uint8 (coefficient-major, channel inner) =
  round(128 · c) + 128 rounded to a multiple of 8 (band 1) or 16 (bands 2-3), clamped (a reader
  takes (b − 128) / 128).

Axes: SPZ stores RUB, the 3DGS PLY's frame (RDF) turned half a turn about x (base.py), as Niantic's
library and splat-transform convert. radfield writes version 3 with fractionalBits = the most, up to
16, that keep every coordinate within 24 bits (Niantic's library writes 12; readers take the header's).
Version 4 (zstd streams, "NGSP" before any compression) is refused in one line.
"""

from __future__ import annotations

import gzip
import struct
import zlib
from pathlib import Path

import numpy as np

from radfield.core.kinds.gaussian import Gaussians
from radfield.errors import RadfieldError
from radfield.model_formats.base import (HALF_TURN_X, ModelFormat, checked, cpu, gaussians, opacity_logit, suffix_is,
                                         turned, unit_quats)
from radfield.util.atomic import atomic_write_bytes

MAGIC = 0x5053474E
HEADER = struct.Struct("<IIIBBBB")
COLOR_SCALE = 0.15
MAX_FRACTIONAL_BITS = 16
SH1_BITS, SH_REST_BITS = 5, 4          # Niantic's defaults: band 1 in 5 bits, bands 2-3 in 4
FLAG_EXTENSIONS = 0x2
SQRT1_2 = 0.7071067811865476


def _round(x: np.ndarray) -> np.ndarray:
    """Half away from zero, as C's round."""
    return np.sign(x) * np.floor(np.abs(x) + 0.5)


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(_round(x), 0, 255).astype(np.uint8)


def fractional_bits(means: np.ndarray) -> int:
    """The most fractional bits (≤ 16) that keep every coordinate within a signed 24-bit integer."""
    biggest = float(np.abs(means).max()) if means.size else 0.0
    if biggest == 0.0:
        return MAX_FRACTIONAL_BITS
    bits = int(np.floor(np.log2((2**23 - 1) / biggest)))
    return min(bits, MAX_FRACTIONAL_BITS)


def spz_bytes(g: Gaussians, version: int = 3, sh1_bits: int = SH1_BITS, sh_rest_bits: int = SH_REST_BITS) -> bytes:
    """The gzip-compressed SPZ file of `g` (see the module docstring)."""
    if version not in (2, 3):
        raise ValueError(f"SPZ version {version} is not written (2 or 3)")
    g = turned(g, HALF_TURN_X)
    n, degree = len(g), g.sh_degree
    means = cpu(g.means).astype(np.float64)
    bits = fractional_bits(means)
    if bits < 0:
        raise RadfieldError(f"spz holds positions within ±{2**23 - 1:,} world units (24-bit fixed point); "
                            f"this model reaches {np.abs(means).max():g}")
    fixed = _round(means * 2.0**bits).astype(np.int64) & 0xFFFFFF
    positions = np.stack([(fixed >> s) & 0xFF for s in (0, 8, 16)], -1).astype(np.uint8)   # (N, 3, 3)
    alphas = _u8(255 / (1 + np.exp(-cpu(g.opacities).astype(np.float64))))
    colours = _u8(cpu(g.sh[:, 0, :]).astype(np.float64) * (COLOR_SCALE * 255) + 127.5)
    scales = _u8((cpu(g.log_scales).astype(np.float64) + 10) * 16)
    q = unit_quats(g)[:, [1, 2, 3, 0]]                        # x y z w
    if version == 3:
        largest = np.abs(q).argmax(1)
        q = q * np.where(q[np.arange(n), largest] < 0, -1.0, 1.0)[:, None]
        comp = largest.astype(np.uint64)
        for i in range(4):
            keep = largest != i
            mag = np.clip(np.floor(511 * np.abs(q[:, i]) / SQRT1_2 + 0.5), 0, 511).astype(np.uint64)
            word = (comp << np.uint64(10)) | ((q[:, i] < 0).astype(np.uint64) << np.uint64(9)) | mag
            comp = np.where(keep, word, comp)
        rotations = np.frombuffer(comp.astype("<u4").tobytes(), np.uint8).reshape(n, 4)
    else:
        q = q * np.where(q[:, 3] < 0, -1.0, 1.0)[:, None]
        rotations = _u8(q[:, :3] * 127.5 + 127.5)
    sh = cpu(g.sh[:, 1:, :]).astype(np.float64)               # (N, K-1, 3): coefficient-major, channel inner
    bucket = np.array([1 << (8 - sh1_bits)] * min(3, sh.shape[1]) + [1 << (8 - sh_rest_bits)] * max(0, sh.shape[1] - 3))
    quantised = _round(sh * 128) + 128
    quantised = np.floor((quantised + bucket[None, :, None] // 2) / bucket[None, :, None]) * bucket[None, :, None]
    sh_bytes = np.clip(quantised, 0, 255).astype(np.uint8)
    header = HEADER.pack(MAGIC, version, n, degree, bits, 0, 0)
    body = b"".join(a.tobytes() for a in (positions, alphas, colours, scales, rotations, sh_bytes))
    return gzip.compress(header + body, compresslevel=9, mtime=0)


def read_spz(path: str | Path) -> Gaussians:
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise RadfieldError(f"{path}: cannot read ({error.strerror or error})") from None
    if raw[:4] == b"NGSP":
        version = struct.unpack("<I", raw[4:8])[0] if len(raw) >= 8 else "?"
        raise RadfieldError(f"{path}: SPZ version {version} (zstd streams) is not read by radfield; "
                            "write version 3 (splat-transform: --spz-version 3)")
    try:
        data = gzip.decompress(raw)
    except (OSError, EOFError, zlib.error) as error:
        raise RadfieldError(f"{path}: not an SPZ file (not a complete gzip stream: {error})") from None
    if len(data) < HEADER.size:
        raise RadfieldError(f"{path}: damaged SPZ file ({len(data)} bytes, shorter than its 16-byte header)")
    magic, version, n, degree, bits, flags, _ = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise RadfieldError(f"{path}: not an SPZ file (magic {magic:#010x}, not 0x5053474e)")
    if version not in (2, 3):
        raise RadfieldError(f"{path}: SPZ version {version} is not read (radfield reads versions 2 and 3)")
    if n == 0:
        raise RadfieldError(f"{path}: the SPZ file holds no Gaussians")
    if degree > 3:
        raise RadfieldError(f"{path}: SH degree {degree} in the SPZ file (radfield holds degrees 0-3)")
    if bits > 23:
        raise RadfieldError(f"{path}: damaged SPZ file ({bits} fractional bits in a 24-bit coordinate)")
    k = (degree + 1) ** 2 - 1
    rot_bytes = 4 if version >= 3 else 3
    sizes = (9 * n, n, 3 * n, 3 * n, rot_bytes * n, 3 * k * n)
    need = HEADER.size + sum(sizes)
    if len(data) < need or (len(data) > need and not flags & FLAG_EXTENSIONS):
        raise RadfieldError(f"{path}: damaged SPZ file ({len(data) - HEADER.size} bytes of splat data, "
                            f"{need - HEADER.size} for {n} splats of SH degree {degree}, version {version})")
    offsets = np.cumsum((HEADER.size,) + sizes)
    part = lambda i: np.frombuffer(data, np.uint8, sizes[i], offsets[i])
    p = part(0).reshape(n, 3, 3).astype(np.int64)
    fixed = p[..., 0] | (p[..., 1] << 8) | (p[..., 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = fixed / 2.0**bits
    alphas = part(1).astype(np.float64) / 255
    dc = ((part(2).reshape(n, 3).astype(np.float64) / 255) - 0.5) / COLOR_SCALE
    log_scales = part(3).reshape(n, 3).astype(np.float64) / 16 - 10
    r = part(4).reshape(n, rot_bytes)
    if version >= 3:
        comp = r.astype(np.uint32) @ np.array([1, 1 << 8, 1 << 16, 1 << 24], np.uint32)
        largest = (comp >> 30).astype(np.int64)
        q = np.zeros((n, 4))
        for i in (3, 2, 1, 0):
            skip = largest == i
            value = SQRT1_2 * (comp & 511).astype(np.float64) / 511 * np.where((comp >> 9) & 1, -1.0, 1.0)
            q[:, i] = np.where(skip, 0.0, value)
            comp = np.where(skip, comp, comp >> 10)
        q[np.arange(n), largest] = np.sqrt(np.clip(1 - (q ** 2).sum(1), 0, None))
    else:
        xyz = r.astype(np.float64) / 127.5 - 1
        q = np.concatenate([xyz, np.sqrt(np.clip(1 - (xyz ** 2).sum(1), 0, None))[:, None]], 1)
    rest = (part(5).reshape(n, k, 3).astype(np.float64) - 128) / 128
    sh = np.concatenate([dc[:, None, :], rest], 1)
    g = gaussians(means, log_scales, q[:, [3, 0, 1, 2]], sh, opacity_logit(alphas))
    return checked(turned(g, HALF_TURN_X), path, "SPZ file")


def write_spz(g: Gaussians, path: Path) -> dict:
    data = spz_bytes(g)
    atomic_write_bytes(path, data)
    return {"gaussians": len(g), "bytes": len(data)}


FORMAT = ModelFormat(
    name="spz", suffixes=(".spz",),
    summary="Niantic's SPZ (version 3, gzip), about a tenth of a PLY",
    loses="positions 24-bit fixed point (2^-16 world units for a model within ±128, fewer fractional "
          "bits beyond); log σ 8 bits in steps of 1/16 over [-10, 5.94] (clamped); rotation 3 × 9 bits "
          "and signs (smallest three); opacity 8 bits of sigmoid; DC colour 8 bits, steps of 0.026 in "
          "f_dc over ±3.33; SH band 1 in steps of 1/16, bands 2-3 of 1/8, over [-1, 1]",
    read=read_spz, write=write_spz, exact=False, recognises=suffix_is(".spz"))
