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

import math

import torch

from radfield.core import kinds
from radfield.core.geometry.cameras import Camera
from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.core.kinds import PixelRay
from radfield.core.kinds.gaussian import EWA_BLUR, Gaussians
from radfield.core.kinds.neural import NeuralPrimitives, density_window, ellipsoid_radius_sq
from radfield.core.render.kernels import ALPHA_MAX, ALPHA_MIN
from radfield.core.render.rasterize import T_MIN
from radfield.core.render.sh import sh_to_color


def neural_density(prims: NeuralPrimitives, i: int, x: torch.Tensor) -> torch.Tensor:
    """σ_i(x) for points x (S, 3): the cos-MLP inside the bounding ellipsoid, 0 outside (eq. 5-6),
    times the window 1.5 (1 − r²) for a windowed model."""
    mu, s = prims.means[i], torch.exp(prims.log_scales[i])
    r2 = ellipsoid_radius_sq(mu, prims.log_scales[i], prims.quats[i], x)
    u = (x - mu) / s.max()
    sigma = torch.cos(prims.omega0 * (u @ prims.w1[i].T + prims.b1[i])) @ prims.w2[i] + prims.b2[i]
    sigma = sigma * density_window(prims, r2)
    return torch.where(r2 <= 1.0, sigma, torch.zeros_like(sigma))


def quadrature_optical_depth(prims: NeuralPrimitives, i: int, origin: torch.Tensor, direction: torch.Tensor,
                             l_min: float = 0.0, scan: int = 4001, intervals: int = 4000) -> float:
    """I = (1/max(s)) ∫ σ_i(o + ℓ d̂) dℓ over ℓ ≥ l_min, numerically (float64); σ windowed where
    prims.window (its integrand then falls to 0 at the chord's ends)."""
    prims = prims.to(dtype=torch.float64)
    o, d = origin.double(), direction.double() / direction.double().norm()
    mu, s = prims.means[i], torch.exp(prims.log_scales[i])
    rot = quat_to_rotmat(prims.quats[i][None])[0]

    def inside(l):
        return bool(((((o + l * d) - mu) @ rot) / s).norm() <= 1.0)

    # every point of the ellipsoid lies within max(s) of μ: scan that stretch of the ray
    centre = float((mu - o) @ d)
    lo, hi = max(l_min, centre - s.max().item()), max(l_min, centre + s.max().item())
    if hi <= lo:
        return 0.0
    ls = torch.linspace(lo, hi, scan, dtype=torch.float64)
    mask = ((((o + ls[:, None] * d) - mu) @ rot) / s).norm(dim=-1) <= 1.0
    idx = torch.nonzero(mask).squeeze(1)
    if idx.numel() == 0:
        return 0.0

    def bisect(a, b):  # inside(a) != inside(b): locate the boundary
        ia = inside(a)
        for _ in range(80):
            m = 0.5 * (a + b)
            if inside(m) == ia:
                a = m
            else:
                b = m
        return 0.5 * (a + b)

    first, last = idx[0].item(), idx[-1].item()
    l_in = ls[first].item() if first == 0 else bisect(ls[first - 1].item(), ls[first].item())
    l_out = ls[last].item() if last == scan - 1 else bisect(ls[last].item(), ls[last + 1].item())
    if l_in == ls[0].item() and l_min > centre - s.max().item():
        l_in = l_min  # the ray starts inside the primitive
    # composite Simpson on [l_in, l_out]; σ evaluated without the inside test (we are inside)
    t = torch.linspace(l_in, l_out, 2 * intervals + 1, dtype=torch.float64)
    x = o + t[:, None] * d
    u = (x - mu) / s.max()
    sigma = torch.cos(prims.omega0 * (u @ prims.w1[i].T + prims.b1[i])) @ prims.w2[i] + prims.b2[i]
    sigma = sigma * density_window(prims, ellipsoid_radius_sq(mu, prims.log_scales[i], prims.quats[i], x))
    weights = torch.ones_like(t)
    weights[1:-1:2], weights[2:-1:2] = 4.0, 2.0
    h = (l_out - l_in) / (2 * intervals)
    return float((weights * sigma).sum() * h / 3.0) / s.max().item()


def gaussian_pixel_alpha(prims: Gaussians, i: int, camera: Camera, u: float, v: float) -> float:
    """EWA splat weight of Gaussian i at image point (u, v), straight from the 3DGS formulas."""
    w2c = torch.linalg.inv(camera.c2w)
    p = w2c[:3, :3] @ prims.means[i].double() + w2c[:3, 3]
    x, y, z = p.tolist()
    lim_x = (camera.cx / camera.fx + 0.15 * camera.width / camera.fx, (camera.width - camera.cx) / camera.fx + 0.15 * camera.width / camera.fx)
    lim_y = (camera.cy / camera.fy + 0.15 * camera.height / camera.fy, (camera.height - camera.cy) / camera.fy + 0.15 * camera.height / camera.fy)
    tx = z * min(max(x / z, -lim_x[0]), lim_x[1])
    ty = z * min(max(y / z, -lim_y[0]), lim_y[1])
    jac = torch.tensor([[camera.fx / z, 0, -camera.fx * tx / z**2], [0, camera.fy / z, -camera.fy * ty / z**2]], dtype=torch.float64)
    rot = quat_to_rotmat(prims.quats[i][None].double())[0]
    cov3 = rot @ torch.diag(torch.exp(2 * prims.log_scales[i].double())) @ rot.T
    cov2 = jac @ w2c[:3, :3] @ cov3 @ w2c[:3, :3].T @ jac.T + EWA_BLUR * torch.eye(2, dtype=torch.float64)
    delta = torch.tensor([u - (camera.fx * x / z + camera.cx), v - (camera.fy * y / z + camera.cy)], dtype=torch.float64)
    # 3DGS evaluates a splat only inside the square of radius ceil(3 √λ_max) around its mean
    radius = math.ceil(3.0 * math.sqrt(float(torch.linalg.eigvalsh(cov2)[-1])))
    if abs(float(delta[0])) > radius or abs(float(delta[1])) > radius:
        return 0.0
    power = -0.5 * float(delta @ torch.linalg.inv(cov2) @ delta)
    return min(ALPHA_MAX, float(torch.sigmoid(prims.opacities[i].double())) * math.exp(power))


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
