"""Recolouring and appearance transfer (paper §6.2) on the SH colour of selected primitives.

    - recolor: {select: SELECTION, multiply: [r, g, b] | set: [r, g, b] | hue: degrees, falloff: f}
    - transfer: {select: SELECTION, from: OTHER_RUN_OR_MODEL, steps: 200, views: 24, size: 48}
    - transfer: {select: SELECTION, images: POSED_DATASET, split: train, steps: 200, views: 24, size: 64,
                 background: [1, 1, 1]}

A primitive's colour along d is c(d) = Σ_k Y_k(d) coeffs_k + 0.5 (3DGS convention). Selections
act on primitive centres (select.py's all/box/sphere/plane with falloff), plus
`density_above: v` (primitives whose peak density — neural: max of σ over samples of the
ellipsoid, in units of the primitive's size, σ windowed for a windowed model; Gaussians: sigmoid
opacity — exceeds v). With a falloff of weight w the new coefficients are (1 − w)·old + w·new.
Unselected primitives (w = 0) are left bit-identical.
- multiply m: c' = m ⊙ c exactly for every direction: DC' = m ⊙ DC + (m − 1)·0.5 / Y_0, higher
  bands' coefficients multiplied by m.
- hue θ: c' = H c with H the rotation by θ about the grey axis (1,1,1)/√3 (H keeps grey fixed, so
  the +0.5 offset is unchanged): every coefficient's RGB vector is multiplied by H; exact.
- set rgb: DC' = (rgb − 0.5)/Y_0; the higher bands are scaled per channel by rgb / DC colour
  (DC colour floored at 0.02, ratio capped at 4), keeping the view-dependent part proportional.
- transfer: the SH of the selected primitives only (geometry frozen) is fitted to renders of the
  reference field (`from`, in the same world frame) from views around the selection, or to a set
  of posed photos (`images`: a NeRF-synthetic folder, a nerfstudio transforms.json or its folder,
  a COLMAP dataset; cameras in the dataset's world frame, which is the model's): `views` of the
  split's images, evenly spaced, downscaled by an integer factor so the longer side is at most
  `size` px, composited on `background` (RGBA), which the renders use too.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import torch

from radfield.errors import RadfieldError
from radfield.core import kinds
from radfield.core.splat.sh import C0
from radfield.edit.field import Field
from radfield.edit.model_operand import load_operand
from radfield.edit.select import number, vector, weights
from radfield.edit.spec import check_keys, operation


def peak_density(prims, samples: int = 128, seed: int = 0) -> torch.Tensor:
    """Per primitive, as its kind measures it (radfield.core.kinds: peak_density): neural, the max
    of σ at `samples` points of its ellipsoid (its centre, the ends of its axes and random points),
    in the primitive's own units (windowed where prims.window: neural_density.neural_sigma); Gaussians,
    sigmoid opacity."""
    return kinds.of(prims).peak_density(prims, samples, seed)


def primitive_weights(prims, selection, falloff: float, where: str) -> np.ndarray:
    """Weight (P,) of each primitive: select.py's selections of centres, or `density_above`."""
    if isinstance(selection, Mapping) and set(selection) == {"density_above"}:
        level = number(selection, "density_above", where)
        return (peak_density(prims).cpu().double().numpy() > level).astype(np.float64)
    return weights(selection, prims.means.detach().cpu().double().numpy(), falloff, where)


def hue_matrix(degrees: float) -> np.ndarray:
    """Rotation by `degrees` about the grey axis (1,1,1)/√3 (Rodrigues' formula)."""
    a = math.radians(degrees)
    k = np.ones(3) / math.sqrt(3)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) * math.cos(a) + math.sin(a) * cross + (1 - math.cos(a)) * np.outer(k, k)


def recolored_sh(sh: torch.Tensor, args, where: str) -> torch.Tensor:
    """New SH (P, K, 3) for the chosen rule (module docstring)."""
    modes = [m for m in ("multiply", "set", "hue") if m in args]
    if len(modes) != 1:
        raise RadfieldError(f"{where}: give exactly one of multiply, set, hue (got {modes or 'none'})")
    mode = modes[0]
    dc, rest = sh[:, :1], sh[:, 1:]
    if mode == "multiply":
        m = torch.as_tensor(vector(args, "multiply", where), dtype=sh.dtype)
        if (m < 0).any():
            raise RadfieldError(f"{where}.multiply: factors must be >= 0, got {m.tolist()}")
        return torch.cat([dc * m + (m - 1) * 0.5 / C0, rest * m], 1)
    if mode == "hue":
        h = torch.as_tensor(hue_matrix(number(args, "hue", where)), dtype=sh.dtype)
        return sh @ h.T
    rgb = torch.as_tensor(vector(args, "set", where), dtype=sh.dtype)
    if (rgb < 0).any():
        raise RadfieldError(f"{where}.set: colours must be >= 0, got {rgb.tolist()}")
    old = torch.clamp_min(dc * C0 + 0.5, 0.02)
    ratio = torch.clamp(rgb / old, 0.0, 4.0)
    return torch.cat([((rgb - 0.5) / C0).expand_as(dc), rest * ratio], 1)


def _selection(args, where: str):
    if "select" not in args:
        raise RadfieldError(f"{where}.select: required (all, box, sphere, plane or density_above)")
    return args["select"], number(args, "falloff", where, default=0.0)


@operation("recolor")
def recolor(fld: Field, args, ctx) -> Field:
    where = ctx.where
    check_keys(args, {"select", "falloff", "multiply", "set", "hue"}, where)
    selection, falloff = _selection(args, where)
    w = primitive_weights(fld.prims, selection, falloff, f"{where}.select")
    new_sh = recolored_sh(fld.prims.sh.detach(), args, where)
    idx = torch.as_tensor(np.flatnonzero(w > 0))
    prims = fld.prims.map(lambda x: x.clone())
    wt = torch.as_tensor(w[idx.numpy()], dtype=prims.sh.dtype)[:, None, None]
    # only the selected rows are written: the others stay bit-identical
    prims.sh[idx] = torch.where(wt == 1, new_sh[idx], (1 - wt) * fld.prims.sh[idx] + wt * new_sh[idx])
    out = fld.with_prims(prims, fld.tet.copy(), fld.bary.copy())
    out.notes.append({"operation": "recolor", "selected": int(idx.numel()), "total": len(prims)})
    ctx.log(f"recolor: {idx.numel()} of {len(prims)} primitives")
    return out


def dataset_targets(path, split: str, views: int, size: int, background, where: str):
    """(cameras, images (H, W, 3) float32) of `views` evenly spaced images of a posed dataset split,
    downscaled so that the longer side is at most `size` px."""
    from radfield.datasets.readers import load_dataset

    data = load_dataset(path, split, 1, background)
    if not data.posed:
        raise RadfieldError(f"{where}.images: {path} has no camera poses (give a posed dataset; photos need `radfield reconstruct` first)")
    first = data.views[0].camera
    downscale = max(1, math.ceil(max(first.width, first.height) / size))
    data = load_dataset(path, split, downscale, background)
    pick = np.unique(np.linspace(0, len(data) - 1, min(views, len(data))).round().astype(int))
    cameras = data.cameras
    return [cameras[i] for i in pick], [data.load_image(int(i))[0] for i in pick]


@operation("transfer")
def transfer(fld: Field, args, ctx) -> Field:
    """Appearance transfer (§6.2): fit the SH of the selected primitives to renders of another field
    or to posed images."""
    from radfield.edit import retrain

    where = ctx.where
    check_keys(args, {"select", "falloff", "from", "images", "split", "background", "steps", "views", "size"}, where)
    selection, falloff = _selection(args, where)
    sources = [k for k in ("from", "images") if k in args]
    if len(sources) != 1:
        raise RadfieldError(f"{where}.from: required (the reference run or model file), or images: a posed dataset "
                            f"(give exactly one, got {sources or 'none'})")
    if "from" in args and any(k in args for k in ("split", "background")):
        raise RadfieldError(f"{where}: split and background go with images:, not from:")
    steps = int(number(args, "steps", where, default=200, positive=True))
    views = int(number(args, "views", where, default=24, positive=True))
    size = int(number(args, "size", where, default=48 if "from" in args else 64, positive=True))
    w = primitive_weights(fld.prims, selection, falloff, f"{where}.select")
    idx = np.flatnonzero(w > 0)
    if idx.size == 0:
        raise RadfieldError(f"{where}.select: selects no primitive")
    if "from" in args:
        reference = load_operand(args["from"], "from", ctx)
        background = retrain.BACKGROUND
        cameras = retrain.orbit_around(fld.prims, idx, views, size)
        with torch.no_grad():
            targets = [retrain.render_image(reference.prims, cam) for cam in cameras]
    else:
        split = args.get("split", "train")
        background = tuple(vector(args, "background", where)) if "background" in args else retrain.BACKGROUND
        if not all(0.0 <= c <= 1.0 for c in background):
            raise RadfieldError(f"{where}.background: expected numbers in [0, 1], got {list(background)}")
        path = ctx.path(args["images"], "images")
        try:
            cameras, targets = dataset_targets(path, split, views, size, background, where)
        except RadfieldError as error:
            message = str(error)
            raise RadfieldError(message if message.startswith(where) else f"{where}.images: {message}") from None
    prims, figures = retrain.fit_colors(fld.prims, idx, cameras, targets, steps, ctx.seed, background)
    out = fld.with_prims(prims, fld.tet.copy(), fld.bary.copy())
    out.notes.append({"operation": "transfer", "selected": int(idx.size), "source": sources[0], "views": len(cameras),
                      **figures})
    what = "reference" if "from" in args else f"{len(cameras)} images"
    ctx.log(f"transfer: {idx.size} primitives, PSNR vs {what} {figures['psnr_before']:.2f} -> {figures['psnr_after']:.2f} dB")
    return out
