"""Anti-aliasing in the renderer: sub-pixel ray jitter and supersampled pixels (the third remedy,
a minimum primitive footprint, is a training rule: core/train/footprint.py).

The renderer point-samples one ray through each pixel centre, (j + 0.5, i + 0.5) (core/geometry/cameras.py);
images, from a camera or a path tracer, average each pixel's area. An edge that crosses a pixel is
then seen by training at one fixed sub-pixel phase per view, and a model can fit that phase (a
primitive's hard boundary placed just so) in every training view while a held-out view, whose
pixels fall on the edge at other phases, sees the fit fail (docs/studies/edges-supersampling.md).
The remedies, all outside the render kernels:

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
"""

from __future__ import annotations

from dataclasses import replace

import torch

from radfield.core.geometry.cameras import Camera
from radfield.core.render.rasterize import Render, render


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
