"""Bake a trained (or edited) model for delivery: drop primitives no training view can see, and
optionally store the tensors as float16.

Edits need no folding: an edited model is already plain primitive parameters (radfield.edit writes
the deformed means, scales, rotations and colours), so baking reads any model file as it is.

Pruning criterion. In view v, primitive i adds w_ivp = T_ivp α_ivp to pixel p (paper eq. 4: its
transmittance-weighted alpha). Its coverage in that view, W_iv = Σ_p w_ivp, comes from one backward
pass: with the colour of every primitive set to a constant c_i (SH degree 0) the render is
C_p = Σ_i w_ivp c_i + T_p·bg, so ∂(Σ_p C_p)/∂c_i = W_iv exactly, whatever kernel computed α (the
fused kernels are untouched: the gradient flows only through the compositing). Because weights are
non-negative, max_p w_ivp ≤ W_iv, so a primitive with max_v W_iv < min_weight has a
transmittance-weighted alpha below min_weight at every pixel of every training view — hidden behind
others (T ≈ 0, or cut off by early termination), outside every frustum, or transparent — and is
removed. The bound makes the rule conservative: a large, faint primitive may be kept although its
per-pixel weight is below the threshold.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable, Sequence

import torch

from radfield.core.render.antialias import render_model
from radfield.core.geometry.cameras import Camera
from radfield.core import kinds
from radfield.core.kinds import Primitives
from radfield.core.splat.sh import C0

DEFAULT_MIN_WEIGHT = 1.0 / 255.0  # below one 8-bit level in every pixel of every training view


def coverage(prims: Primitives, cameras: Sequence[Camera], *, background=(1.0, 1.0, 1.0),
             near: float = 0.01, on_view: Callable[[], None] | None = None) -> torch.Tensor:
    """(P,) max over the views of W_iv = Σ_p T α (module docstring), on the model's device."""
    best = torch.zeros(len(prims), device=prims.means.device, dtype=prims.means.dtype)
    frozen = prims.map(lambda t: t.detach())
    for camera in cameras:
        # the primitives as this view sees them (a time-conditioned or relightable kind's at_view): the
        # probe stands in for the colour the view composites, which such a kind computes from more
        # than `sh` (a probe in `sh` alone would reach the view's colour scaled by the light, or not
        # at all where the view's colour is clamped at 0)
        seen = kinds.of(frozen).at_view(frozen, camera)
        probe = torch.zeros(len(prims), 1, 3, device=best.device, dtype=best.dtype, requires_grad=True)
        # with the model's own n × n rays a pixel: W_iv sums each pixel's mean T α of its rays (still ≤ 1 a pixel)
        out = render_model(replace(seen, sh=probe), camera, background=background, near=near)
        (grad,) = torch.autograd.grad(out.color[..., 0].sum(), probe, allow_unused=True)
        if grad is not None:  # None: no primitive reached a pixel
            best = torch.maximum(best, grad[:, 0, 0] / C0)
        if on_view is not None:
            on_view()
    return best


def prune(prims: Primitives, weights: torch.Tensor, min_weight: float = DEFAULT_MIN_WEIGHT):
    """(kept primitives, boolean keep mask (P,)): those with coverage at least `min_weight`."""
    keep = weights >= min_weight
    return prims.select(keep), keep


def to_fp16_and_back(prims: Primitives) -> Primitives:
    """The model as a float16 file holds it (what a reader of that file renders)."""
    return prims.map(lambda t: t.to(torch.float16).to(t.dtype))
