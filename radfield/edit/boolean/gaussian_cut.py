"""A boolean's boundary on a Gaussian field (3DGS, e.g. an imported PLY): Gaussians have no line
integral to mask and no local retraining, so the boundary is refined by splitting instead.

Each straddling Gaussian (classified over its 3σ ellipsoid, classification.py) is split along its
longest axis e into the moment-matched halves of its density (the two halves of a normal of
deviation σ: means ±σ√(2/π) along e, deviation σ√(1 − 2/π) there), each with opacity o / (2√(1 − 2/π))
so that the pair keeps the parent's opacity integrated along e; the halves are classified again,
and those still straddling are split again, SPLIT_ROUNDS times (the band of uncertain Gaussians
thins by 0.6 a round). What still straddles then is kept when its centre is kept. A cut face is
not capped: a 3DGS object is a shell, and its cut stays open (the neural path seeds and retrains a
cap, caps.py).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.core.kinds.gaussian import Gaussians
from radfield.edit.boolean.classification import classify
from radfield.edit.boolean.shapes import Shape
from radfield.edit.compose import concat_prims

SPLIT_ROUNDS = 4
HALF_OFFSET = math.sqrt(2 / math.pi)       # the mean of a half-normal, in σ
HALF_DEVIATION = math.sqrt(1 - 2 / math.pi)  # its deviation, in σ


def halves(g: Gaussians) -> Gaussians:
    """Every Gaussian of `g` as the two moment-matched halves of its density along its longest axis
    (module docstring): the first halves of all, then the second halves."""
    axis = g.log_scales.argmax(-1)
    rows = torch.arange(len(g))
    e = quat_to_rotmat(g.quats)[rows, :, axis]                      # (P, 3) the longest axis
    sigma = torch.exp(g.log_scales[rows, axis])
    offset = (HALF_OFFSET * sigma)[:, None] * e
    log_scales = g.log_scales.clone()
    log_scales[rows, axis] += math.log(HALF_DEVIATION)
    # o' = o / (2 √(1 − 2/π)): the pair integrates to the parent's opacity along e (as a logit)
    opacity = (torch.sigmoid(g.opacities) / (2 * HALF_DEVIATION)).clamp(max=0.99)
    child = lambda sign: Gaussians(means=g.means + sign * offset, log_scales=log_scales, quats=g.quats, sh=g.sh,
                                   opacities=torch.logit(opacity), supersample=g.supersample)
    return concat_prims(child(1.0), child(-1.0))


def refine_boundary(straddlers: Gaussians, keep_fn, shape: Shape | None, keep_inside: bool) -> tuple[Gaussians, dict]:
    """The straddling Gaussians of one field, split where they straddle the mask `keep_fn` (points
    -> bool) and kept where it keeps them (module docstring); the figures: splits made, Gaussians
    kept."""
    kept, todo, splits = [], straddlers.map(lambda t: t.detach()), 0
    for _ in range(SPLIT_ROUNDS):
        if len(todo) == 0:
            break
        todo = halves(todo)
        splits += len(todo) // 2
        classes = classify(todo, keep_fn, shape, keep_inside)
        kept.append(todo.select(torch.as_tensor(np.flatnonzero(classes == 1))))
        todo = todo.select(torch.as_tensor(np.flatnonzero(classes == -1)))
    centres = keep_fn(todo.means.double().numpy()) if len(todo) else np.zeros(0, bool)
    kept.append(todo.select(torch.as_tensor(np.flatnonzero(centres))))
    out = kept[0]
    for part in kept[1:]:
        out = concat_prims(out, part)
    return out, {"splits": splits, "boundary_kept": len(out)}
