"""Local retraining of a boolean's boundary (Neural Impostor §4.2): the straddling primitives and the
cap discs are refitted (edit/retrain.py) to the teacher, the exact boolean field: its density at
points in their ellipsoids (eq. 15) and its masked renders from views around them."""

from __future__ import annotations

import time

import numpy as np
import torch

from radfield.core.kinds import NeuralPrimitives
from radfield.core.kinds import neural_density
from radfield.edit import retrain
from radfield.edit.compose import concat_prims


def retrain_boundary(frozen: NeuralPrimitives, straddlers: NeuralPrimitives, caps: NeuralPrimitives,
                     mask_ids: np.ndarray, masks: list, steps: int, views: int, size: int, ctx, note: dict) -> NeuralPrimitives:
    """frozen ∪ (straddlers ∪ caps refitted to the teacher) (frozen first, bit-identical). The
    straddlers carry their masks (mask_ids into `masks`); the teacher's seconds, the log line
    before the fit and the fit's figures go in `note` and ctx.log."""
    student = concat_prims(straddlers, caps)
    teacher = concat_prims(concat_prims(frozen, straddlers), caps)
    t_mask = np.concatenate([np.full(len(frozen), -1), mask_ids, np.full(len(caps), -1)])
    pts, target = density_teacher(student, len(straddlers), mask_ids, masks, ctx.seed)
    cameras = retrain.orbit_around(student, np.arange(len(student)), views, size)
    t1 = time.perf_counter()
    targets = [retrain.teacher_render(teacher, cam, t_mask, masks) for cam in cameras]
    note["teacher_seconds"] = round(time.perf_counter() - t1, 2)
    ctx.log(f"boolean {note['op']}: kept {len(frozen)}, dropped {note['dropped']}, retraining {len(straddlers)} + {len(caps)} seeded")
    fitted, figures = retrain.retrain(frozen, student, pts, target, cameras, targets, steps1=steps, steps2=steps,
                                      seed=ctx.seed, log=ctx.log)
    note.update({k: round(v, 3) if isinstance(v, float) else v for k, v in figures.items()})
    return concat_prims(frozen, fitted.to(dtype=frozen.means.dtype))


def density_teacher(student: NeuralPrimitives, n_masked: int, mask_ids, masks, seed: int, per_prim: int = 48):
    """Points in the student's ellipsoids and the teacher's density there: Σ over the masked
    (straddling) primitives of m(x)·σ/max s, plus the cap primitives' own density (eq. 15)."""
    u = neural_density.unit_ball_samples(per_prim, seed + 1)
    s64 = student.to(dtype=torch.float64).map(lambda t: t.detach())
    pts = neural_density.ellipsoid_points(s64, u).reshape(-1, 3)
    target = torch.zeros(len(pts), dtype=torch.float64)
    with torch.no_grad():
        for lo in range(0, len(pts), 2048):
            x = pts[lo:lo + 2048]
            dens = neural_density.pair_density(s64, x)                             # (Q, S)
            weight = torch.ones_like(dens)
            for k in np.unique(mask_ids).tolist():
                cols = torch.as_tensor(np.flatnonzero(mask_ids == k))
                m = torch.as_tensor(masks[k](x.numpy()), dtype=torch.float64)
                weight[:, cols] = m[:, None]
            target[lo:lo + 2048] = (dens * weight).sum(1)
    return pts, target
