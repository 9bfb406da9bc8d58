"""Slow, obviously-correct references for the fast renderer (tests compare against these).

- `quadrature_optical_depth`: integrates σ along one ray numerically. The ellipsoid is found by a
  dense inside/outside scan refined by bisection (not the analytic quadratic), then composite
  Simpson quadrature of the MLP density of eq. 5-6 — times the window 1.5 (1 − r²) at every node
  for a windowed model (prims.window) — no closed form anywhere.
- `gaussian_pixel_alpha`: a splat's weight at one image point, straight from the 3DGS formulas.
- `reference_render`: a per-pixel loop that composites every primitive front to back (eq. 4) with
  the same rules as the fast path (sort by centre depth, α ≤ 0.99, skip α < 1/255, stop when the
  transmittance would fall below 1e-4); each kind's α comes from its `reference_alpha` hook
  (core/kinds/), which calls the functions above.
Everything runs in float64 with Python loops; keep images tiny.
"""

from __future__ import annotations


import torch

from radfield.core import kinds
from radfield.core.geometry.cameras import Camera
from radfield.core.kinds import PixelRay
from radfield.core.splat.kernels import ALPHA_MIN
from radfield.core.render.rasterize import T_MIN
from radfield.core.splat.sh import sh_to_color


def reference_render(prims: kinds.Primitives, camera: Camera, background=(1.0, 1.0, 1.0),
                     near: float = 0.01) -> torch.Tensor:
    """(H, W, 3) float64 image by a loop over pixels and, inside, over primitives in depth order."""
    prims = kinds.of(prims).at_view(prims, camera)   # as render() draws it (kinds/base.py: at_view)
    kind = kinds.of(prims)
    prims = prims.to(dtype=torch.float64)
    c2w = camera.c2w
    w2c = torch.linalg.inv(c2w)
    campos = c2w[:3, 3]
    depth = prims.means @ w2c[2, :3] + w2c[2, 3]
    order = torch.argsort(depth, stable=True).tolist()
    colors = sh_to_color(prims.sh, torch.nn.functional.normalize(prims.means - campos, dim=-1), prims.sh_degree)
    image = torch.zeros(camera.height, camera.width, 3, dtype=torch.float64)
    bg = torch.tensor(background, dtype=torch.float64)
    for row in range(camera.height):
        for col in range(camera.width):
            u, v = col + 0.5, row + 0.5
            d_cam = torch.tensor([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0], dtype=torch.float64)
            direction = c2w[:3, :3] @ (d_cam / d_cam.norm())
            ray = PixelRay(camera, u, v, campos, direction, near, near * d_cam.norm().item())
            transmittance, pixel = 1.0, torch.zeros(3, dtype=torch.float64)
            for i in order:
                alpha = kind.reference_alpha(prims, i, ray, float(depth[i]))
                if alpha < ALPHA_MIN:
                    continue
                if transmittance * (1.0 - alpha) < T_MIN:
                    break
                pixel += transmittance * alpha * colors[i]
                transmittance *= 1.0 - alpha
            image[row, col] = pixel + transmittance * bg
    return image
