"""`radfield demo-scene smoke`: an animated heterogeneous volume with exact ground truth, written as
a D-NeRF dataset (NeRF-synthetic files whose frames carry a `time` ξ_t in [0, 1]).

The volume is a few coloured puffs, each an anisotropic Gaussian density with one colour:

    σ_k(x, ξ) = ρ_k(ξ) exp(−½ |S_k(ξ)⁻¹ R_k(ξ)ᵀ (x − μ_k(ξ))|²),   c(x) = Σ_k σ_k c_k / Σ_k σ_k

(dense, nearly opaque cores and semi-transparent edges). Over ξ each puff moves, grows and turns,
smoothly and in closed form: μ_k(ξ) = p_k + v_k ξ + a_k sin(π ξ), S_k(ξ) = S_k (1 + g_k ξ),
R_k(ξ) = the rotation by θ_k + ω_k ξ about the axis u_k, and ρ_k(ξ) = ρ_k / (1 + g_k ξ), so the
optical depth through a core stays the same while the puff spreads.

Rendering is the emission-absorption integral C = ∫ T(l) σ(x) c(x) dl + T_end · background,
T(l) = exp(−∫₀ˡ σ), by quadrature. Along a ray each puff's density is a 1D Gaussian in l, so its
optical depth over any interval is closed form (erf): the span of the ray where any puff matters
(±5 standard deviations of each) is cut into `segments` equal pieces; each piece's opacity
T_j − T_{j+1} is exact, and its colour is the puffs' colours weighted by their exact shares of
the piece's optical depth (exact where one puff fills a piece, O(h²) where puffs overlap). So
alpha = 1 − T_end is exact for any number of pieces and only the colour of overlaps converges with
them: with SEGMENTS = 128 the colour moves by < 3e-4 from 128 to 256 pieces (about 1/15 of 1/255;
4x less per doubling, O(h²)), and it matches an independent midpoint ray marcher of the densities
as written to 1e-4 (tests/test_dynamic_data.py). One ray through each pixel centre: the puffs are
smooth over several pixels. Images are premultiplied RGBA on a transparent background (0), as the
other demo scenes'.

Cameras and files: demo/timelapse.py (every camera of scenes.orbit_cameras' spiral at every
time k / (times − 1)). The puffs stay inside every camera's view at every time (their 4σ
ellipsoids within VIEW_RADIUS of the origin).
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from radfield.core.geometry.cameras import Camera, pixel_rays
from radfield.demo.scenes import CAMERA_ANGLE_X, CAMERA_RADIUS

SEGMENTS = 128       # quadrature pieces per ray (see the module docstring)
WINDOW = 5.0         # a puff matters along a ray within this many of its standard deviations there
# Radius around the origin that every camera sees whole: the sphere inscribed in the view cone.
VIEW_RADIUS = CAMERA_RADIUS * math.sin(CAMERA_ANGLE_X / 2)


@dataclass(frozen=True)
class Puff:
    """One Gaussian puff (see the module docstring for how each field moves it over ξ)."""

    centre: tuple        # p
    velocity: tuple      # v
    swirl: tuple         # a: the sin(π ξ) detour
    scales: tuple        # S: standard deviations along the puff's own axes at ξ = 0
    growth: float        # g: scales × (1 + g ξ)
    axis: tuple          # u: the turning axis
    angle: float         # θ at ξ = 0 (radians)
    spin: float          # ω: radians turned over ξ ∈ [0, 1]
    density: float       # ρ at ξ = 0
    colour: tuple

    def centre_at(self, xi: float) -> np.ndarray:
        return np.add(self.centre, np.multiply(self.velocity, xi)) + np.multiply(self.swirl, math.sin(math.pi * xi))

    def scales_at(self, xi: float) -> np.ndarray:
        return np.multiply(self.scales, 1.0 + self.growth * xi)

    def rotation_at(self, xi: float) -> np.ndarray:
        """Rodrigues' rotation by θ + ω ξ about u."""
        u = np.asarray(self.axis, float) / np.linalg.norm(self.axis)
        angle = self.angle + self.spin * xi
        cross = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
        return np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross

    def density_at(self, xi: float) -> float:
        return self.density / (1.0 + self.growth * xi)

    def extent_at(self, xi: float) -> float:
        """Radius around the origin of the puff's 4σ ellipsoid (bounded by its largest axis)."""
        return float(np.linalg.norm(self.centre_at(xi)) + 4.0 * self.scales_at(xi).max())


PUFFS = (
    Puff((-0.3, -0.15, -0.1), (0.35, -0.15, 0.25), (0.0, 0.1, 0.05), (0.18, 0.11, 0.13), 0.3,
         (0.0, 0.3, 1.0), 0.3, 1.6, 18.0, (0.95, 0.5, 0.12)),
    Puff((0.3, 0.15, -0.1), (-0.25, 0.15, 0.3), (0.0, 0.0, 0.1), (0.1, 0.17, 0.12), 0.35,
         (1.0, 0.0, 0.4), 0.0, -1.2, 18.0, (0.15, 0.4, 0.95)),
    Puff((0.1, -0.35, 0.2), (0.2, 0.45, -0.45), (0.1, 0.0, 0.0), (0.14, 0.14, 0.085), 0.5,
         (0.3, 1.0, 0.0), 0.5, 2.0, 18.0, (0.2, 0.8, 0.3)),
    Puff((-0.1, 0.35, 0.2), (-0.25, -0.35, -0.4), (-0.1, 0.0, 0.1), (0.12, 0.085, 0.155), 0.4,
         (0.0, 1.0, 0.5), -0.4, 1.0, 18.0, (0.85, 0.2, 0.7)),
    Puff((0.0, 0.0, -0.1), (0.0, 0.0, 0.45), (0.15, 0.15, 0.0), (0.085, 0.085, 0.085), 1.0,
         (1.0, 1.0, 1.0), 0.0, 0.0, 25.0, (0.95, 0.92, 0.85)),
)


def ray_colours(origin: torch.Tensor, directions: torch.Tensor, xi: float, puffs=PUFFS,
                segments: int = SEGMENTS) -> tuple[torch.Tensor, torch.Tensor]:
    """Premultiplied colour (R, 3) and alpha (R,) of rays from `origin` (3,) along unit
    `directions` (R, 3) through the volume at time ξ on a transparent background (float64).

    Per ray and puff, x = o + l d gives |M (x − μ)|² = A l² + 2 B l + Cq (M = S⁻¹Rᵀ), so
    σ_k(l) = ρ e^{−m/2} e^{−A (l − l*)²/2} with l* = −B/A, m = Cq − B²/A, and its optical depth from
    −∞ to l is F_k(l) = ρ e^{−m/2} √(π/2A) (1 + erf(√(A/2) (l − l*)))."""
    dtype = torch.float64
    origin, directions = origin.to(dtype), directions.to(dtype)
    frames = [(torch.tensor(p.centre_at(xi), dtype=dtype),
               torch.tensor(np.diag(1 / p.scales_at(xi)) @ p.rotation_at(xi).T, dtype=dtype),
               p.density_at(xi)) for p in puffs]
    u = torch.stack([directions @ m.T for _, m, _ in frames], -1)                  # (R, 3, K): M d
    w = torch.stack([m @ (origin - mu) for mu, m, _ in frames], -1)                # (3, K): M (o − μ)
    rho = torch.tensor([r for _, _, r in frames], dtype=dtype)
    a = (u * u).sum(1)                                                              # (R, K)
    b = (u * w).sum(1)
    peak_depth = rho * torch.exp(-0.5 * ((w * w).sum(0) - b * b / a))               # ρ e^{−m/2}
    centre, spread = -b / a, torch.sqrt(a / 2)
    total = peak_depth * torch.sqrt(2 * math.pi / a)                                # each puff's whole optical depth
    colours = torch.tensor([p.colour for p in puffs], dtype=dtype)

    def depth(l: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:                # F_k(l) of rays `rows`: (H, ..., K)
        shape = (-1,) + (1,) * (l.dim() - 1) + (len(puffs),)
        t, s, c = (x[rows].view(shape) for x in (total, spread, centre))
        return 0.5 * t * (1 + torch.special.erf(s * (l[..., None] - c)))

    # the span of each ray where some puff matters, in front of the camera; rays that meet no
    # puff are transparent and cost nothing more
    matters = total > 1e-7
    half = WINDOW / torch.sqrt(a)
    lo = torch.where(matters, centre - half, torch.inf).amin(1).clamp(min=0.0)
    hi = torch.where(matters, centre + half, -torch.inf).amax(1)
    hit = torch.nonzero(hi > lo)[:, 0]
    colour = torch.zeros(len(directions), 3, dtype=dtype)
    before = depth(torch.zeros(len(hit), dtype=dtype), hit)                         # F_k(0)
    alpha = torch.zeros(len(directions), dtype=dtype)
    alpha[hit] = 1 - torch.exp(-(total[hit] - before).sum(-1))                      # 1 − T(∞), exact
    steps = torch.linspace(0, 1, segments + 1, dtype=dtype)
    grid = lo[hit, None] + (hi - lo)[hit, None] * steps                             # (H, N + 1)
    per_puff = depth(grid, hit) - before[:, None, :]                                # ∫₀ˡ σ_k, (H, N + 1, K)
    transmittance = torch.exp(-per_puff.sum(-1))                                    # T(l_j), exact
    opacity = transmittance[:, :-1] - transmittance[:, 1:]                          # ∫ T σ over each piece, exact
    piece = per_puff[:, 1:] - per_puff[:, :-1]                                      # each puff's optical depth there
    weight = opacity / piece.sum(-1).clamp(min=1e-30)                               # per unit optical depth
    colour[hit] = torch.einsum("hn,hnk,kc->hc", weight, piece, colours)
    return colour, alpha


def render_smoke(camera: Camera, xi: float, puffs=PUFFS, segments: int = SEGMENTS) -> np.ndarray:
    """Premultiplied RGBA (H, W, 4) float32 of the volume at time ξ through the pixel centres."""
    directions, _ = pixel_rays(camera, dtype=torch.float64)
    colour, alpha = ray_colours(camera.center, directions.reshape(-1, 3), xi, puffs, segments)
    rgba = torch.cat([colour, alpha[:, None]], -1).reshape(camera.height, camera.width, 4)
    return rgba.numpy().astype(np.float32)


def generate_smoke(out_dir: str | os.PathLike, n_train: int | None = None, n_test: int | None = None,
                   times: int | None = None, size: int = 64, seed: int = 0,
                   progress: Callable[[int], None] | None = None, held_out_times: bool = False) -> Path:
    """Write the smoke scene as a D-NeRF folder (demo/timelapse.py: every camera at every
    time, or the test cameras at the midpoints with `held_out_times`; defaults 36 + 4 cameras × 24 times)."""
    from radfield.demo.timelapse import generate_dynamic

    return generate_dynamic("smoke", out_dir, n_train, n_test, times, size, seed, progress, held_out_times)


def describe() -> dict:
    """What scene.json says of the volume: the exact puffs and how they move."""
    return {
        "description": "coloured Gaussian puffs that move, grow and turn over time (a heterogeneous volume)",
        "density": "sigma_k(x, t) = rho_k / (1 + g_k t) * exp(-|diag(1 / (scales_k (1 + g_k t))) R_k(t)^T "
                   "(x - mu_k(t))|^2 / 2); mu_k(t) = centre + velocity t + swirl sin(pi t); R_k(t) = rotation "
                   "by angle + spin t about axis; colour: the sigma-weighted mix of the puffs' colours",
        "rendering": f"emission-absorption quadrature, {SEGMENTS} pieces per ray with exact opacities; "
                     "one ray per pixel centre; premultiplied RGBA on a transparent background",
        "puffs": [dataclasses.asdict(p) for p in PUFFS],
    }


render = render_smoke  # what demo/timelapse.py calls
