"""Neural primitives as 3D Gaussians by moment matching: the neural kind's `to_gaussians` (for
export to 3DGS tools; delivery/refine.py then fits them to the model's renders).

A neural primitive's world-space extinction inside its ellipsoid is ρ(x) = max(0, σ(x)) / max(s)
(σ of paper eq. 5-6, times the window 1.5 (1 − r²) of a windowed model, prims.window; the
renderer's optical depth is I = ∫ρ dℓ). Each primitive becomes K
Gaussians: its samples are split into K clusters (weighted k-means), and each cluster j is replaced
by the Gaussian density with the same mass, mean and covariance,

    M_j = ∫ρ dV,   m_j = ∫ρ x dV / M_j,   C_j = ∫ρ (x − m_j)(x − m_j)ᵀ dV / M_j,

integrated on a regular grid over the ellipsoid (midpoint rule, with Sheppard's h²/12 per cell).
Means and covariances weigh the samples by max(0, ρ); the total mass uses the signed ρ (the
renderer clamps the line integral, not the density: eq. 9), shared between the components in
proportion to their positive mass (signed mass is 0.65 dB better on the blobs demo).
A Gaussian density M·N(x; m, C) seen along a unit direction d has peak optical depth
τ(d) = M / (2π √(det C · dᵀC⁻¹d)) (its projection onto the plane ⊥ d); the 3DGS opacity is
1 − exp(−τ̄) with τ̄ the mean of τ(d) over directions. Colour (all SH bands) is copied. Dividing a
primitive's density between several Gaussians keeps the composite exact where they overlap
(equal colours: C = c (1 − Π Tⱼ) in any order) and makes each one thinner, where the 3DGS
opacity profile o·g(r) is closer to the true 1 − exp(−τ g(r)).
"""

from __future__ import annotations

import math

import torch

from radfield.core.geometry.rotations import quat_to_rotmat, rotmat_to_quat
from radfield.core.kinds.gaussian import Gaussians
from radfield.core.kinds.neural_density import density_window
from radfield.core.splat.sh import fibonacci_sphere

GRID = 14          # samples per ellipsoid axis (about 1400 inside the ball)


LLOYD_STEPS = 8    # k-means iterations when splitting a primitive into components


MIN_OPACITY = 1e-3  # Gaussians fainter than this are dropped (3DGS skips α < 1/255 anyway)


MAX_OPACITY = 0.99


def _ball_grid(n: int, dtype) -> tuple[torch.Tensor, float]:
    """Cell centres (N, 3) of an n³ grid over [−1, 1]³ that lie in the unit ball, and the cell size."""
    h = 2.0 / n
    g = -1 + h * (torch.arange(n, dtype=dtype) + 0.5)
    y = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    return y[y.norm(dim=-1) <= 1], h


def neural_density_samples(prims, grid: int = GRID):
    """World points x (P, N, 3) on the grid inside each ellipsoid, their sample masses ρ(x) dV (P, N),
    each primitive's total mass with the signed density (P,), and the per-axis Sheppard variance
    (P, 3) of one cell in the ellipsoid's frame."""
    y, h = _ball_grid(grid, prims.means.dtype)
    y = y.to(prims.means.device)
    rot = quat_to_rotmat(prims.quats)
    s = prims.scales
    smax = s.amax(-1)
    offset = torch.einsum("pij,pj,nj->pni", rot, s, y)                         # R S y
    u = offset / smax[:, None, None]                                            # eq. 5: u = (x − μ)/max(s)
    phase = prims.omega0 * (torch.einsum("pnj,pkj->pnk", u, prims.w1) + prims.b1[:, None, :])
    sigma = (prims.w2[:, None, :] * torch.cos(phase)).sum(-1) + prims.b2[:, None]   # eq. 6
    # the grid point y is x in the unit-sphere frame (x = μ + R S y): its r² is |y|², the
    # quantity _ball_grid kept the points inside by
    sigma = sigma * density_window(prims, (y * y).sum(-1))
    cell_volume = h**3 * s.prod(-1)
    signed = sigma / smax[:, None] * cell_volume[:, None]
    return prims.means[:, None, :] + offset, torch.clamp_min(signed, 0.0), signed.sum(-1).clamp_min(0.0), (h * s) ** 2 / 12


def _cluster(x: torch.Tensor, mass: torch.Tensor, k: int) -> torch.Tensor:
    """Weighted k-means labels (P, N) of the samples, started along each primitive's principal axis."""
    total = mass.sum(-1, keepdim=True).clamp_min(1e-30)
    mean = (mass[..., None] * x).sum(1) / total
    d = x - mean[:, None]
    cov = torch.einsum("pn,pni,pnj->pij", mass, d, d) / total[..., None]
    evals, evecs = torch.linalg.eigh(cov)
    axis, spread = evecs[..., -1], torch.sqrt(evals[..., -1].clamp_min(0))
    steps = torch.linspace(-1, 1, k, dtype=x.dtype, device=x.device)
    centres = mean[:, None] + steps[None, :, None] * (spread[:, None, None] * axis[:, None, :])
    for _ in range(LLOYD_STEPS):
        labels = torch.cdist(x, centres).argmin(-1)
        onehot = torch.nn.functional.one_hot(labels, k).to(x.dtype) * mass[..., None]   # (P, N, k)
        weight = onehot.sum(1)
        moved = torch.einsum("pnk,pni->pki", onehot, x) / weight[..., None].clamp_min(1e-30)
        centres = torch.where(weight[..., None] > 0, moved, centres)
    return torch.cdist(x, centres).argmin(-1)


def gaussians_from_neural(prims, components: int = 1, grid: int = GRID,
                          chunk: int = 512) -> Gaussians:
    """`components` moment-matched Gaussians per neural primitive (see the module docstring);
    components that carry no density (or less opacity than MIN_OPACITY) are left out."""
    if components < 1:
        raise ValueError("components must be at least 1")
    prims = prims.to(dtype=torch.float64)
    dirs = fibonacci_sphere(64).to(prims.means.device)
    parts = []
    for lo in range(0, len(prims), chunk):
        p = prims.select(slice(lo, lo + chunk))
        x, mass, total, cell_var = neural_density_samples(p, grid)
        labels = _cluster(x, mass, components) if components > 1 else torch.zeros_like(mass, dtype=torch.long)
        rot = quat_to_rotmat(p.quats)
        sheppard = rot @ torch.diag_embed(cell_var) @ rot.transpose(1, 2)
        for j in range(components):
            w = mass * (labels == j)
            wsum = w.sum(-1).clamp_min(1e-30)
            m = w.sum(-1) * total / mass.sum(-1).clamp_min(1e-30)
            mean = (w[..., None] * x).sum(1) / wsum[:, None]
            d = x - mean[:, None]
            cov = torch.einsum("pn,pni,pnj->pij", w, d, d) / wsum[:, None, None] + sheppard
            evals, evecs = torch.linalg.eigh(cov)
            evecs = evecs * torch.where(torch.linalg.det(evecs) < 0, -1.0, 1.0)[:, None, None]  # a rotation
            # mean peak optical depth over view directions: τ(d) = M / (2π √(det C · dᵀC⁻¹d))
            quad = (dirs[None] ** 2 / evals[:, None, :]).sum(-1)                  # dᵀC⁻¹d in the eigenframe
            tau = m[:, None] / (2 * math.pi * torch.sqrt(evals.prod(-1)[:, None] * quad))
            opacity = (-torch.expm1(-tau.mean(-1))).clamp(max=MAX_OPACITY)
            keep = opacity >= MIN_OPACITY
            parts.append(Gaussians(
                means=mean[keep], log_scales=0.5 * torch.log(evals[keep]), quats=rotmat_to_quat(evecs[keep]),
                sh=p.sh[keep], opacities=torch.logit(opacity[keep]),
            ))
    return Gaussians(**{name: torch.cat([getattr(g, name) for g in parts]).to(torch.float32)
                        for name in ("means", "log_scales", "quats", "sh", "opacities")})
