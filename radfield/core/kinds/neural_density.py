"""The neural primitive's density σ(x) at points (paper eq. 5-6), where the renderer needs only its
line integral in closed form: evaluated at points of each primitive or of the whole field, sampled
in the unit ball, and integrated numerically along a ray (the closed form's slow reference).

σ(x) = W2 · cos(ω0 (W1 u + b1)) + b2 with u = (x − μ) / max(s), inside the ellipsoid B(μ, R, s),
times the window 1.5 (1 − r²) where the model is windowed (`density_window`). Local retraining,
booleans, remeshing and recolouring (radfield.edit) and the kind's peak density read it here.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.core.splat.kernels import (WINDOW_GAIN, ellipsoid_frame, neural_optical_depth, ray_ellipsoid,
                                         windowed_optical_depth)



def ellipsoid_radius_sq(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                        x: torch.Tensor) -> torch.Tensor:
    """r² = |S⁻¹Rᵀ(x − μ)|² (...,) of points x (..., 3) in the unit-sphere frame of the ellipsoids
    B(μ, R, s) (r² ≤ 1: inside); means, log_scales (..., 3) and quats (..., 4) broadcast against x.
    The one place the window's radius is computed (the point sites' hard inside tests keep their
    own |S⁻¹Rᵀ(x − μ)| ≤ 1, so a hard-edged model's results stay bit for bit)."""
    rot = quat_to_rotmat(quats)
    local = ((x - means)[..., None, :] @ rot)[..., 0, :] * torch.exp(-log_scales)   # Rᵀ(x − μ) / s
    return (local * local).sum(-1)


def density_window(prims, r2: torch.Tensor) -> torch.Tensor | float:
    """The factor on σ at points of squared ellipsoid radius r2 = |S⁻¹Rᵀ(x − μ)|² (inside: r2 ≤ 1):
    1.5 (1 − r2) for a windowed model, 1 for a hard-edged one. Every evaluation of a neural
    primitive's density at points takes it from here (the renderer integrates it in closed form)."""
    return WINDOW_GAIN * (1.0 - r2) if prims.window else 1.0


# --- densities at points --------------------------------------------------------------------------

def unit_ball_samples(n: int, seed: int = 0) -> torch.Tensor:
    """(n, 3) float64 points of the closed unit ball: the centre, the 6 axis ends, the 8 cube
    diagonals on the sphere, then uniform random points (a fixed set: classification is repeatable)."""
    axes = torch.cat([torch.eye(3), -torch.eye(3)]).double()
    diag = torch.tensor([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)], dtype=torch.float64) / math.sqrt(3)
    g = torch.Generator().manual_seed(seed)
    m = max(n - 15, 0)
    d = torch.nn.functional.normalize(torch.randn(m, 3, generator=g, dtype=torch.float64), dim=-1)
    r = torch.rand(m, 1, generator=g, dtype=torch.float64) ** (1 / 3)
    return torch.cat([torch.zeros(1, 3, dtype=torch.float64), axes, diag, d * r])[:n]


def ellipsoid_points(prims, u: torch.Tensor) -> torch.Tensor:
    """Points (P, S, 3) μ + R S u of each primitive's ellipsoid for unit-ball points u (S, 3)."""
    rot = quat_to_rotmat(prims.quats)
    return prims.means[:, None] + torch.einsum("pij,sj->psi", rot * prims.scales[:, None, :], u.to(prims.means.dtype))


def neural_sigma(prims, x: torch.Tensor) -> torch.Tensor:
    """Density σ_i (P, S) of each primitive i at its own points x (P, S, 3), windowed where
    prims.window (no ellipsoid test: the callers' points lie in the ellipsoids)."""
    smax = prims.scales.amax(-1)
    u = (x - prims.means[:, None]) / smax[:, None, None]
    phase = prims.omega0 * (torch.einsum("psj,pnj->psn", u, prims.w1) + prims.b1[:, None])
    sigma = (torch.cos(phase) * prims.w2[:, None]).sum(-1) + prims.b2[:, None]
    if not prims.window:
        return sigma
    r2 = ellipsoid_radius_sq(prims.means[:, None], prims.log_scales[:, None], prims.quats[:, None], x)
    return sigma * density_window(prims, r2)


def pair_density(prims, x: torch.Tensor) -> torch.Tensor:
    """σ_j(x_q) / max s_j (Q, P) of every primitive at every point, 0 outside its ellipsoid: the
    extinction per world unit that primitive j adds at x_q (the renderer's optical depth is its
    integral along the ray); σ windowed where prims.window."""
    m, smax = ellipsoid_frame(prims.means, prims.log_scales, prims.quats)
    rel = x[:, None] - prims.means[None]                                   # (Q, P, 3)
    inside = torch.einsum("pij,qpj->qpi", m, rel).norm(dim=-1) <= 1.0
    u = rel / smax[:, None]
    phase = prims.omega0 * (torch.einsum("qpj,pnj->qpn", u, prims.w1) + prims.b1)
    sigma = (torch.cos(phase) * prims.w2).sum(-1) + prims.b2
    # the inside test is the norm of M (x − μ), not the window's ellipsoid_radius_sq, whose rounding
    # differs: points on the sphere to rounding (unit_ball_samples puts 14 a primitive there) keep
    # the side this norm gives them, with or without the window
    if prims.window:
        sigma = sigma * density_window(prims, ellipsoid_radius_sq(prims.means, prims.log_scales, prims.quats, x[:, None]))
    return torch.where(inside, sigma / smax, torch.zeros_like(sigma))


def field_density(prims, points: np.ndarray | torch.Tensor, chunk: int = 4096) -> np.ndarray:
    """D(x) = Σ_i [x ∈ B_i] max(σ_i(x), 0) / max(s_i) at points (Q, 3): the field's density for the
    boolean field B = [D > ε] (eq. 13). Candidates by a KD-tree of centres within the largest radius."""
    x = torch.as_tensor(np.asarray(points, np.float64))
    p64 = prims.to(dtype=torch.float64)
    out = np.zeros(len(x))
    if len(prims) == 0 or len(x) == 0:
        return out
    means = p64.means.detach().numpy()
    reach = float(p64.scales.amax().detach())
    tree = cKDTree(means)
    with torch.no_grad():
        for lo in range(0, len(x), chunk):
            xs = x[lo:lo + chunk]
            lists = tree.query_ball_point(xs.numpy(), reach)
            qi = np.repeat(np.arange(len(xs)), [len(c) for c in lists])
            if qi.size == 0:
                continue
            pj = np.concatenate([np.asarray(c, np.int64) for c in lists])
            sub = p64.select(torch.as_tensor(pj))
            # per pair: one point, one primitive
            d = _pair_density_1to1(sub, xs[torch.as_tensor(qi)])
            out[lo:lo + chunk] += np.bincount(qi, weights=np.maximum(d.numpy(), 0), minlength=len(xs))
    return out


def _pair_density_1to1(prims, x: torch.Tensor) -> torch.Tensor:
    """σ_j(x_j) / max s_j for matched rows (primitive j, point j), 0 outside the ellipsoid; σ
    windowed where prims.window."""
    m, smax = ellipsoid_frame(prims.means, prims.log_scales, prims.quats)
    rel = x - prims.means
    inside = torch.einsum("pij,pj->pi", m, rel).norm(dim=-1) <= 1.0
    phase = prims.omega0 * (torch.einsum("pj,pnj->pn", rel / smax[:, None], prims.w1) + prims.b1)
    sigma = (torch.cos(phase) * prims.w2).sum(-1) + prims.b2
    if prims.window:   # r² shared, the inside test unchanged (pair_density)
        sigma = sigma * density_window(prims, ellipsoid_radius_sq(prims.means, prims.log_scales, prims.quats, x))
    return torch.where(inside, sigma / smax, torch.zeros_like(sigma))


# --- the line integral along rays: in closed form, and by quadrature (its reference) ------------

def neural_line_integral(prims, origins: torch.Tensor, dirs: torch.Tensor,
                         l_min: torch.Tensor | float = 0.0) -> torch.Tensor:
    """Optical depth I of every primitive along every ray: origins, dirs (R, 3) with unit dirs ->
    (R, P). Integration starts at ray distance l_min (near plane, or 0 for a camera inside).
    A convenience wrapper over the same per-pair kernel the rasteriser uses (windowed where
    prims.window is set)."""
    m, smax = ellipsoid_frame(prims.means, prims.log_scales, prims.quats)       # (P,3,3), (P,)
    rel = origins[:, None, :] - prims.means[None]                               # (R, P, 3)
    o_ell = torch.einsum("pij,rpj->rpi", m, rel)
    d_ell = torch.einsum("pij,rj->rpi", m, dirs)
    l_in_raw, l_out, hit = ray_ellipsoid(o_ell, d_ell)
    l_min = torch.as_tensor(l_min, dtype=l_in_raw.dtype, device=l_in_raw.device)
    l_in = torch.maximum(l_in_raw, l_min[:, None] if l_min.ndim == 1 else l_min)
    w = prims.omega0 * prims.w1                                                 # (P, N, 3)
    a = torch.einsum("pnj,rj->rpn", w, dirs)
    c = torch.einsum("pnj,rpj->rpn", w, rel / smax[:, None]) + prims.omega0 * prims.b1
    if prims.window:
        return windowed_optical_depth(l_in_raw, l_in, l_out, hit, (d_ell * d_ell).sum(-1), a, c, prims.w2, prims.b2,
                                      1.0 / smax)
    return neural_optical_depth(l_in, l_out, hit, a, c, prims.w2, prims.b2, 1.0 / smax)


# --- by quadrature -------------------------------

def primitive_density(prims, i: int, x: torch.Tensor) -> torch.Tensor:
    """σ_i(x) for points x (S, 3): the cos-MLP inside the bounding ellipsoid, 0 outside (eq. 5-6),
    times the window 1.5 (1 − r²) for a windowed model."""
    mu, s = prims.means[i], torch.exp(prims.log_scales[i])
    r2 = ellipsoid_radius_sq(mu, prims.log_scales[i], prims.quats[i], x)
    u = (x - mu) / s.max()
    sigma = torch.cos(prims.omega0 * (u @ prims.w1[i].T + prims.b1[i])) @ prims.w2[i] + prims.b2[i]
    sigma = sigma * density_window(prims, r2)
    return torch.where(r2 <= 1.0, sigma, torch.zeros_like(sigma))


def quadrature_optical_depth(prims, i: int, origin: torch.Tensor, direction: torch.Tensor,
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
