"""`stn-ply`: the PLY of the official Splat the Net code (huynguyenbao/splat-the-net,
scene/gaussian_model_mlp_HB.py `save_ply`, drawn by huynguyenbao/diff-gaussian-mlp-max-rasterization,
cuda_rasterizer/forward_mlp.cu and mlp_kernels.cu `forward_mlp_siren`), read as radfield's neural
kind. Read only.

Layout. One vertex element, float32, in this order: ``x y z nx ny nz f_dc_0..2 f_rest_0..3(K−1)−1
opacity opacity_volr scale_0..2 rot_0..3 frequencies_0..3N−1 phases_0..N−1 amplitudes_0..N−1
offsets`` (N = 8 hidden units, the CUDA kernel's fixed width; K = 16 SH coefficients). What each
becomes (the official renderer's activations reproduced, every number kept as stored):

    x y z                 -> means
    scale_i               -> log_scales (the code draws exp(scale_i): radfield's convention)
    rot_0..3              -> quats, w x y z (normalised when drawn, by both)
    f_dc_*, f_rest_*      -> sh (P, K, 3): f_rest channel-major, as the 3DGS PLY; colour
                             max(SH(μ − campos) + 0.5, 0) in both
    frequencies_{a·N+k}   -> w1[k, a]   (the file holds W1 transposed: axis-major)
    phases_k              -> b1[k]
    amplitudes_k          -> w2[k]
    offsets               -> b2
    (not stored)          -> omega0 = 30: the renderer passes ω·frequencies and ω·phases (ω = 30,
                             `self.omega`), so σ = W2·cos(30 (W1 u + b1)) + b2, radfield's density
                             with ω0 = 30 and no rescaling
    opacity, opacity_volr -> ignored: the MLP renderer never reads them (`opacity` reaches the
                             kernel's unused conic_opacity, `opacity_volr` is not passed at all)
    nx ny nz              -> ignored (zeros)

The same model. The official kernel draws what radfield's hard-edged neural primitive draws
(window = False: the code has no 1.5 (1 − r²) window): the chord of the ray through the ellipsoid
|S⁻¹Rᵀ(x − μ)| ≤ 1 (radius 1 in units of the scales, s = exp(scale_i)); u = (x − μ)/max(s) in world
axes (not the primitive's rotated frame); the closed-form integral of σ along the chord in units
of max(s), I = (1/max s) ∫σ dℓ; α = min(0.99, 1 − exp(−I)), nothing where I ≤ 0 or α < 1/255;
primitives composited front to back by the camera-space depth of their centres, a pixel stopping
at the first primitive that would take its transmittance below 1e-4 (that one left out); pixel
centres at (j + 0.5, i + 0.5) with the principal point at the image centre.

Where the official renderer differs (numerics and culling, not the model; radfield draws the
exact model):
- its integral divides each unit's term by (ω0 W1_k·d̂ / max(s) + 1e-7) instead of
  ω0 W1_k·d̂ / max(s) (radfield: the exact sinc form): relative error 1e-7 max(s) / |ω0 W1_k·d̂|,
  below float32 rounding unless a frequency row is within ~1e-7 of perpendicular to the ray;
- it culls a primitive whose centre is at camera depth ≤ 0.2 and integrates the whole chord, from
  the entry point even behind the camera; radfield culls by the whole ellipsoid and starts chords
  at the near plane: the same wherever the ellipsoid lies in front of both planes;
- it only visits the tiles of the 3σ box of the EWA footprint of the Gaussian of the same scales
  (variance dilated by 0.3 px², centre clamped to 1.3 × the field of view), which holds the
  projected ellipsoid (1σ) except, possibly, for primitives centred far outside the image;
- its kernel has exactly 8 hidden units; radfield reads any N ≥ 1 with 3N, N and N MLP properties.

Refused in one line naming the property: a file plyfile cannot parse, a missing property, MLP or
``f_rest`` counts out of that layout, a non-finite number, or an out-of-range one (the model
file's bounds, and ω0·|w1| ≤ 1e4). A PLY is this format when its vertex header declares a
``frequencies_*``, ``phases_*``, ``amplitudes_*`` or ``offsets`` property (base.is_stn_ply); a 3DGS
PLY declares none, and the 3DGS reader refuses such a file.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from radfield.core import kinds
from radfield.core.kinds.neural import NeuralPrimitives
from radfield.errors import RadfieldError
from radfield.model_formats.base import ModelFormat, is_stn_ply
from radfield.model_formats.ply_3dgs import REST_COUNTS, read_ply_elements

OMEGA0 = 30.0     # GaussianModelMLP_HB.omega: not in the file, fixed in the official code
WHAT = "Splat the Net PLY"
GEOMETRY = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3")
# radfield's tensor -> the file's properties, for the range messages
PROPERTY_OF = {"means": "x y z", "log_scales": "scale_*", "quats": "rot_*", "w1": "frequencies_*",
               "b1": "phases_*", "w2": "amplitudes_*", "b2": "offsets", "sh": "f_dc_* / f_rest_*"}


def _numbered(have: set[str], prefix: str) -> int:
    return sum(re.fullmatch(re.escape(prefix) + r"\d+", name) is not None for name in have)


def _counts(path: Path, have: set[str]) -> tuple[int, int]:
    """(N hidden units, f_rest count) of the vertex properties `have`, or one error line."""
    missing = [name for name in (*GEOMETRY, "frequencies_0", "phases_0", "amplitudes_0", "offsets") if name not in have]
    if missing:
        raise RadfieldError(f"{path}: not a complete {WHAT} (the vertex element lacks {', '.join(missing)})")
    n = _numbered(have, "phases_")
    wanted = {"frequencies_": 3 * n, "phases_": n, "amplitudes_": n}
    for prefix, count in wanted.items():
        gap = next((f"{prefix}{i}" for i in range(count) if f"{prefix}{i}" not in have), None)
        if _numbered(have, prefix) != count or gap is not None:
            raise RadfieldError(
                f"{path}: a {WHAT} has 3N frequencies_*, N phases_* and N amplitudes_* numbered from 0 "
                f"(N hidden units, 8 in the official code); this one has {_numbered(have, 'frequencies_')}, "
                f"{_numbered(have, 'phases_')} and {_numbered(have, 'amplitudes_')}"
                + (f" ({gap} missing)" if gap is not None and _numbered(have, prefix) == count else ""))
    n_rest = _numbered(have, "f_rest_")
    if n_rest not in REST_COUNTS or any(f"f_rest_{i}" not in have for i in range(n_rest)):
        raise RadfieldError(f"{path}: a {WHAT} has 0, 9, 24 or 45 f_rest properties (f_rest_0 ...), this one {n_rest}")
    return n, n_rest


def read_stn_ply(path: str | Path) -> NeuralPrimitives:
    """The official Splat the Net PLY at `path` as neural primitives (the module docstring's mapping)."""
    path = Path(path)
    ply = read_ply_elements(path, WHAT)
    names = [e.name for e in ply.elements]
    if "vertex" not in names:
        raise RadfieldError(f"{path}: not a {WHAT} (no 'vertex' element; elements: {', '.join(names) or 'none'})")
    v = ply["vertex"]
    n, n_rest = _counts(path, {p.name for p in v.properties})
    count = len(v.data)
    if count == 0:
        raise RadfieldError(f"{path}: the {WHAT} holds no primitives")

    def col(*keys: str) -> np.ndarray:
        """(P, len(keys)) float64 of these properties; one error line at the first non-finite value."""
        try:
            out = np.stack([np.asarray(v[k], np.float64) for k in keys], 1) if keys else np.zeros((count, 0))
        except (ValueError, TypeError) as error:
            raise RadfieldError(f"{path}: not a readable {WHAT} ({error})") from None
        bad = ~np.isfinite(out)
        if bad.any():
            row, j = np.argwhere(bad)[0]
            raise RadfieldError(f"{path}: damaged {WHAT}: '{keys[j]}' is not finite at primitive {row}")
        return out

    rest = col(*(f"f_rest_{i}" for i in range(n_rest))).reshape(count, 3, n_rest // 3).transpose(0, 2, 1)
    sh = np.concatenate([col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :], rest], 1)
    freq = col(*(f"frequencies_{i}" for i in range(3 * n))).reshape(count, 3, n).transpose(0, 2, 1)   # (P, N, 3)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
    with np.errstate(over="ignore"):   # a float64 property beyond float32's range: caught below as not finite
        prims = NeuralPrimitives(
            means=t(col("x", "y", "z")), log_scales=t(col("scale_0", "scale_1", "scale_2")),
            quats=t(col("rot_0", "rot_1", "rot_2", "rot_3")), sh=t(sh),
            w1=t(freq), b1=t(col(*(f"phases_{i}" for i in range(n)))), w2=t(col(*(f"amplitudes_{i}" for i in range(n)))),
            b2=t(col("offsets")[:, 0]), omega0=OMEGA0, window=False)
    for name, tensor in prims.tensors().items():
        if not torch.isfinite(tensor).all():
            row = int(torch.nonzero(~torch.isfinite(tensor.reshape(count, -1)).all(-1))[0])
            raise RadfieldError(f"{path}: {WHAT} out of range: '{PROPERTY_OF.get(name, name)}' at primitive {row} "
                                "(beyond float32)")
    bad = kinds.of(prims).check_values(prims)
    if bad is not None:
        name, row, why = bad
        raise RadfieldError(f"{path}: {WHAT} out of range: '{PROPERTY_OF.get(name, name)}' at primitive {row} ({why})")
    return prims


FORMAT = ModelFormat(
    name="stn-ply", suffixes=(".ply",),
    summary="the official Splat the Net PLY (huynguyenbao/splat-the-net), read as neural primitives",
    loses="nothing the official renderer draws: every number float32 as stored; opacity and opacity_volr, "
          "which it does not draw, are not read",
    read=read_stn_ply, write=None, exact=True, recognises=is_stn_ply, priority=20)
