"""Anti-aliasing: sub-pixel ray jitter, supersampled pixels and a minimum primitive footprint.

The renderer point-samples one ray through each pixel centre, (j + 0.5, i + 0.5) (core/geometry/cameras.py);
images, from a camera or a path tracer, average each pixel's area. An edge that crosses a pixel is
then seen by training at one fixed sub-pixel phase per view, and a model can fit that phase (a
primitive's hard boundary placed just so) in every training view while a held-out view, whose
pixels fall on the edge at other phases, sees the fit fail (docs/studies/edges-supersampling.md).
Three remedies, all outside the render kernels:

Ray jitter (`train.ray_jitter` = a, in pixels; instant-NGP's training rays): every training view
of a step is rendered with its principal point shifted by

    (δx, δy) ~ U(−a/2, a/2)²,   (cx, cy) ← (cx + δx, cy + δy),                                  (1)

so pixel (i, j) samples the ray through (j + 0.5 − δx, i + 0.5 − δy): with a = 1 a uniform point
of the pixel's square. The expected L2 loss over δ is then the loss against the pixel's
box-filtered render, E_δ ‖r(x + δ) − y‖² = ‖(r ∗ box)(x) − y‖² + Var_δ r, so training fits the
area averages that the images hold, plus a variance term that penalises renders which change
within a pixel (sharp edges placed to match one phase). The offsets are drawn from a generator of
(seed, step), so a resumed run draws what the uninterrupted one drew. (Measured: with the L1 + D-SSIM
loss it lowers val by ~2 dB for both kinds on studio; docs/studies/edges-supersampling.md.)

Supersampling (`render.supersample` = n, in training and in every render of the model): each pixel
is the mean of the n × n rays through the centres of an n × n grid of sub-pixels,

    C(i, j) = 1/n² Σ_{a,b} r(j + (a + ½)/n, i + (b + ½)/n),                                  (3)

the midpoint quadrature of the pixel's box filter, so the model is fitted to, and rendered as,
area averages: an edge a few primitives draw is consistent in every view, at any sub-pixel phase.
It costs n² times the pixels (×1.2–1.9 a step at n = 2 on 64×64 views, docs/studies/edges-supersampling.md); the loss, SSIM and
metrics stay at the image's own resolution. The model is then right only rendered the same way:
the train stage stores n in the model (`prims.supersample`, the model file's `supersample` key),
and every render of a model for a user goes through `render_model`, which reads it from there.

Footprint floor (`train.min_footprint` = k, in pixels; Mip-Splatting's 3D filter, Yu et al. 2024,
§4.1, bounds each primitive's size below by the finest sampling interval of the training views):
after every optimiser step every scale axis is raised to at least k pixels of the primitive's
finest training view,

    s_i ← max(s_i, k · min over the views of z / f)                                        (2)

(z/f of the finest view among those whose image holds the centre, radfield.core.train.frequency.footprint
of a point, recomputed with the frequency cap's interval), so no primitive is thinner than k pixels
in any training view and none can fit detail between the pixel centres. A primitive no training
view's image holds is left alone.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import torch

from radfield.core.geometry.cameras import Camera
from radfield.core.train.frequency import footprint, view_stack
from radfield.core.render.rasterize import Render, render
from radfield.core.train.strategy import refresh_interval, stale

PROBE = 1e-4  # scene units: the radius of the point whose footprint gives a view's pixel size z/f


def jitter_offsets(amount: float, count: int, generator: torch.Generator) -> list[tuple[float, float]]:
    """Eq. (1): `count` principal-point offsets (δx, δy) uniform in [−amount/2, amount/2]² pixels
    (all zero, and nothing drawn, when amount is 0)."""
    if amount <= 0:
        return [(0.0, 0.0)] * count
    offsets = (torch.rand(count, 2, generator=generator, dtype=torch.float64) - 0.5) * amount
    return [(float(dx), float(dy)) for dx, dy in offsets]


def shifted(camera: Camera, offset: tuple[float, float]) -> Camera:
    """The camera with its principal point moved by offset (δx, δy) pixels (the same camera at (0, 0))."""
    dx, dy = offset
    return camera if dx == 0 and dy == 0 else replace(camera, cx=camera.cx + dx, cy=camera.cy + dy)


def render_supersampled(prims, camera: Camera, n: int, **kwargs) -> Render:
    """Eq. (3): each pixel the mean of n × n rays through the cell centres of its n × n grid, rendered
    as one view at n times the resolution (the same rays: pixel (i', j') of `camera.scaled(n)` looks
    through ((j' + ½)/n, (i' + ½)/n) of camera) and averaged over n × n blocks. n = 1 is `render`
    itself. Differentiable like render; meta of the large render. For Gaussians the renderer's
    0.3 px² EWA dilation then acts in sub-pixels (0.3/n² of a pixel²): the box filter takes over
    its anti-aliasing role (as Mip-Splatting's 2D filter replaces it by the pixel's footprint)."""
    if n == 1:
        return render(prims, camera, **kwargs)
    out = render(prims, camera.scaled(n), **kwargs)
    h, w = camera.height, camera.width
    pool = lambda t: t.reshape(h, n, w, n, *t.shape[2:]).mean((1, 3))
    return Render(pool(out.color), pool(out.alpha), pool(out.depth), out.meta)


def render_model(prims, camera: Camera, **kwargs) -> Render:
    """A model drawn as it was trained: eq. (3) with its own n (`prims.supersample`, 1 = `render`)."""
    return render_supersampled(prims, camera, prims.supersample, **kwargs)


class FootprintFloor:
    """Eq. (2) during training: `apply(params, step)` after each optimiser step raises
    params["log_scales"] to at least log(k · z/f) of each primitive's finest training view."""

    def __init__(self, cameras: Sequence[Camera], *, pixels: float, near: float, every: int = 100):
        if pixels < 0:
            raise ValueError(f"minimum footprint must be >= 0 pixels, got {pixels}")
        self.views = view_stack(cameras) if pixels > 0 else None
        self.pixels = pixels
        self.near = near
        self.every = max(int(every), 1)
        self._floor = None  # (P,) the floor on log s per primitive (−inf: unseen)

    @classmethod
    def for_training(cls, cameras: Sequence[Camera], cfg: dict, *, near: float) -> "FootprintFloor":
        """The floor of a training run from its `train` config section (refreshed at the frequency cap's interval)."""
        every = refresh_interval(cfg)
        return cls(cameras, pixels=cfg["min_footprint"], near=near, every=every)

    def floor(self, means: torch.Tensor) -> torch.Tensor:
        """log(k · z/f) per primitive (P,) of its finest training view, −inf for primitives no
        training view has in its image. A function of the means alone, so that raising the
        scales never moves the floor (a resumed run applies the floor the uninterrupted run did)."""
        # footprint() of a PROBE-sized primitive: ρ = f · PROBE / z over the views whose image holds the centre
        rho = footprint(means, torch.full_like(means[:, 0], PROBE), self.views, self.near)
        return torch.where(rho > 0, torch.log(self.pixels * PROBE / rho.clamp_min(1e-30)), -math.inf)

    @torch.no_grad()
    def apply(self, params: dict[str, torch.Tensor], step: int) -> None:
        if self.views is None:
            return
        log_scales = params["log_scales"]
        if stale(self._floor, log_scales.shape[0], step, self.every):
            self._floor = self.floor(params["means"].detach())
        # in place and idempotent: scales at or above the floor keep their bits
        torch.maximum(log_scales, self._floor[:, None].to(log_scales), out=log_scales)
