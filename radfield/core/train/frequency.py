"""A per-primitive frequency cap for the density MLP of neural primitives: an anti-aliasing bound.

A neural primitive's density (Splat the Net eq. 5) is σ(x) = w2 · cos(ω0 (W1 u + b1)) + b2 over
u = (x − μ) / max(s). Hidden unit n is a plane wave of angular frequency

    k_n = ω0 ‖W1_n‖                      (radians per unit of u; W1_n: row n of W1)

so its period is 2π / k_n in u, i.e. 2π max(s) / k_n in the scene. A view of focal length f
(pixels) sees the primitive at depth z with

    ρ = f · max(s) / z                   (pixels per unit of u: its projected radius in pixels)

and samples the wave with 2π ρ / k_n pixels per period. Nyquist: at fewer than 2 pixels per
period no view resolves it, and a wave no view resolves can only alias: its line integral
changes with the ray direction, so it fits a different pattern into each training view and
nothing held out (the overfitting of the study docs/studies/quality-omega0.md). The finest sampling any
training view offers is ρ_max = max over the training views in which the primitive is in front
of the camera and inside the image (grown by ρ); the cap is

    k_n ≤ c · ρ_max,   c = train.frequency_cap  (c = π: the Nyquist limit; 0 = no cap)    (1)

(the default c = 2, a period of at least π pixels, was chosen on validation views: docs/studies/frequency-cap.md)

enforced after every optimiser step by a projection (projected Adam):

    W1_n ← W1_n · min(1, c ρ_max / (ω0 ‖W1_n‖)).                                              (2)

So the usable frequency follows each primitive's footprint: on 64×64 views a primitive covers a
few pixels and gets only low frequencies, whatever ω0 is (ω0 still scales the MLP-gradient
statistic that densification thresholds, so it is not free: docs/studies/frequency-cap.md); on 223×398 photos, or close
to a camera, the same primitive may be as detailed as the pixels show. ρ_max depends on the
means and scales only, so it is recomputed every `every` steps, not every step (P × views
projections); `for_training` takes radfield.core.train.strategy.refresh_interval, the greatest common
divisor of the densification and checkpoint intervals, so the bound is refreshed after every
change of the population and at every step a checkpoint can be written at: a resumed run then
recomputes exactly the bound the uninterrupted run used. A primitive that no training view sees
is left alone (no bound by eq. 1).

An absolute bound in units of the primitive (`train.frequency_bound` = K, rad per unit of u; 0 = off)
can be added on top (docs/studies/few-view-captures.md):

    k_n ≤ K                                                                                    (3)

eq. (1) is lax for a primitive that covers many pixels: with ρ_max = 8 px and c = 2 a unit may
oscillate 2.5 periods across the radius, i.e. the primitive carries internal density structure
whose line integrals differ from view to view (tomography with few, nearly co-directional views).
K = π allows at most half a period over the radius whatever the footprint; eq. (2) then projects
onto min(c ρ_max, K) / ω0 (K also binds primitives no view sees).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from radfield.core.geometry.cameras import Camera
from radfield.core.train.strategy import refresh_interval, stale

NYQUIST = math.pi  # c of eq. (1) at which a period spans exactly 2 pixels of the finest view
CAMERA_CHUNK = 16  # views per batched projection (P × 16 depths at a time)


def view_stack(cameras: Sequence[Camera]) -> tuple[torch.Tensor, torch.Tensor]:
    """The views as two tensors: world-to-camera (C, 3, 4) and intrinsics (C, 6) fx fy cx cy W H."""
    w2c = torch.stack([c.w2c[:3] for c in cameras]).float()
    intrinsics = torch.tensor([[c.fx, c.fy, c.cx, c.cy, c.width, c.height] for c in cameras], dtype=torch.float32)
    return w2c, intrinsics


def footprint(means: torch.Tensor, max_scale: torch.Tensor, views: tuple[torch.Tensor, torch.Tensor],
              near: float) -> torch.Tensor:
    """ρ_max (P,): the largest projected radius in pixels, f · max(s) / z, over the views
    (`view_stack`) in which the primitive is beyond the near plane and its disc of radius ρ meets
    the image (f: the larger focal length of the view); 0 where no view sees it."""
    best = torch.zeros_like(max_scale)
    for first in range(0, views[0].shape[0], CAMERA_CHUNK):
        w2c, intr = (v[first:first + CAMERA_CHUNK].to(means) for v in views)
        p = torch.einsum("cij,pj->cpi", w2c[:, :, :3], means) + w2c[:, None, :, 3]   # (C, P, 3)
        z = p[..., 2]
        fx, fy, cx, cy, width, height = (intr[:, k, None] for k in range(6))
        safe_z = z.clamp_min(near)
        rho = torch.maximum(fx, fy) * max_scale / safe_z                               # (C, P)
        px, py = fx * p[..., 0] / safe_z + cx, fy * p[..., 1] / safe_z + cy
        seen = (z > near) & (px > -rho) & (px < width + rho) & (py > -rho) & (py < height + rho)
        best = torch.maximum(best, torch.where(seen, rho, 0.0).amax(0))
    return best


class FrequencyCap:
    """Eq. (1)-(2) during training: `apply(params, step)` after each optimiser step projects the
    rows of params["w1"] onto the ball of radius c · ρ_max / ω0 (in place, no gradient)."""

    def __init__(self, cameras: Sequence[Camera], *, factor: float, omega0: float, near: float, every: int = 100,
                 absolute: float = 0.0):
        if factor < 0 or absolute < 0:
            raise ValueError(f"frequency cap factor and absolute bound must be >= 0, got {factor}, {absolute}")
        self.absolute = absolute  # K of eq. (3), 0 = off
        self.views = view_stack(cameras)
        self.factor = factor
        self.omega0 = omega0
        self.near = near
        self.every = max(int(every), 1)
        self._bound = None  # (P,) the bound on ‖W1_n‖ per primitive

    @classmethod
    def for_training(cls, cameras: Sequence[Camera], cfg: dict, *, omega0: float | None, near: float) -> "FrequencyCap":
        """The cap of a training run from its `train` config section (omega0 None: Gaussians, no cap)."""
        every = refresh_interval(cfg)
        factor = cfg["frequency_cap"] if omega0 else 0.0
        absolute = cfg["frequency_bound"] if omega0 else 0.0
        return cls(cameras, factor=factor, omega0=omega0 or 1.0, near=near, every=every, absolute=absolute)

    @property
    def enabled(self) -> bool:
        return self.factor > 0 or self.absolute > 0

    def bound(self, params: dict[str, torch.Tensor]) -> torch.Tensor:
        """The bound on ‖W1_n‖ per primitive, min(c · ρ_max, K) / ω0 (eq. 1, 3; inf where neither binds)."""
        means, log_scales = params["means"].detach(), params["log_scales"].detach()
        bound = torch.full_like(means[:, 0], math.inf)
        if self.factor > 0:
            rho = footprint(means, torch.exp(log_scales.amax(-1)), self.views, self.near)
            bound = torch.where(rho > 0, self.factor * rho / self.omega0, bound)
        if self.absolute > 0:
            bound = bound.clamp_max(self.absolute / self.omega0)
        return bound

    @torch.no_grad()
    def apply(self, params: dict[str, torch.Tensor], step: int) -> None:
        if not self.enabled or "w1" not in params:
            return
        w1 = params["w1"]
        if stale(self._bound, w1.shape[0], step, self.every):
            self._bound = self.bound(params)
        norms = w1.norm(dim=-1)                                                        # (P, N)
        bound = self._bound[:, None]
        # rows within the bound (and rows projected before: rounding) stay bit for bit as they are,
        # so applying the cap again at a resumed step changes nothing
        shrink = torch.where(norms > bound * (1 + 1e-6), bound / norms.clamp_min(1e-12), 1.0)
        w1.mul_(shrink[..., None])
