"""Classification of primitives by a mask over their ellipsoids (a Gaussian's: its 3σ support, the
kind's support_radius): wholly kept, wholly removed, or straddling the boundary (those are retrained,
or split: gaussian_cut.py)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch

from radfield.core import kinds
from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.core.kinds import neural_density

from radfield.edit.boolean.shapes import Shape

SAMPLES = 64   # points per ellipsoid where no exact test settles a primitive (neural_density.unit_ball_samples)


def classify(prims, keep_fn, shape: Shape | None = None, keep_inside: bool = True) -> np.ndarray:
    """Per primitive: 1 mask is 1 on its whole ellipsoid (kept), 0 wholly 0 (dropped), -1 straddling.
    keep_fn maps points -> bool (the mask). With a shape, the bounding-sphere test on its signed
    distance (exact, 1-Lipschitz) settles most primitives before sampling; keep_inside says
    whether the mask is the shape's inside or its outside."""
    support = kinds.of(prims).support_radius
    if support != 1.0:   # the ellipsoid tested is the primitive's support
        prims = replace(prims, log_scales=prims.log_scales + math.log(support))
    n = len(prims)
    out = np.full(n, -2)
    means = prims.means.detach().cpu().double().numpy()
    reach = prims.scales.detach().cpu().double().amax(-1).numpy()
    if shape is not None and shape.sd is not None:
        d = shape.sd(means)
        if shape.exact_extent is not None:
            rot = quat_to_rotmat(prims.quats.detach().cpu().double()).numpy()
            reach = np.linalg.norm(np.einsum("pji,j->pi", rot, shape.exact_extent) * np.exp(prims.log_scales.detach().cpu().double().numpy()), axis=1)
        inside_all, outside_all = d <= -reach, d >= reach
        out[inside_all] = 1 if keep_inside else 0
        out[outside_all] = 0 if keep_inside else 1
    todo = np.flatnonzero(out == -2)
    if todo.size:
        pts = neural_density.ellipsoid_points(prims.select(torch.as_tensor(todo)).to(dtype=torch.float64).map(lambda t: t.detach().cpu()),
                                       neural_density.unit_ball_samples(SAMPLES)).numpy()
        m = keep_fn(pts.reshape(-1, 3)).reshape(len(todo), SAMPLES)
        out[todo] = np.where(m.all(1), 1, np.where(~m.any(1), 0, -1))
    return out


def mask_classes(prims, mask, shape: Shape | None, keep_inside: bool) -> np.ndarray:
    """`classify` for one field's mask (None: 1 everywhere, every primitive kept)."""
    return np.ones(len(prims), int) if mask is None else classify(prims, mask, shape, keep_inside)
