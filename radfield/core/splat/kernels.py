"""Per pixel-primitive pair kernels: the splatting weights α of one ray through one primitive.

Everything here is elementwise over pairs (leading dims broadcast), so the rasteriser can feed it
flat batches and `torch.compile` can fuse it into one loop.
"""

from __future__ import annotations


import torch

from radfield.core.geometry.rotations import quat_to_rotmat


WINDOW_GAIN = 1.5       # the window 1.5 (1 − r²): the central chord's optical depth is the hard-edged one's

ALPHA_MAX = 0.99        # 3DGS clamp: no primitive is fully opaque, keeps log(1 − α) finite
ALPHA_MIN = 1.0 / 255   # 3DGS skip threshold


def ellipsoid_frame(means, log_scales, quats) -> tuple[torch.Tensor, torch.Tensor]:
    """M = S⁻¹Rᵀ (P, 3, 3) maps world offsets into the unit-sphere frame of the bounding ellipsoid
    B(μ, R, s); also returns max(s) (P,)."""
    rot = quat_to_rotmat(quats)
    inv_s = torch.exp(-log_scales)
    return rot.transpose(-1, -2) * inv_s[..., :, None], torch.exp(log_scales.amax(-1))


def ray_ellipsoid(o_ell: torch.Tensor, d_ell: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Entry and exit distances of rays o + ℓ d̂ through the unit sphere, given o' = M(o − μ) and
    d' = M d̂ (..., 3): solves |o' + ℓ d'|² = 1. Returns (ℓ_in, ℓ_out, hit).

    In the closest-approach form ℓ = ℓ* ∓ √((1 − |p|²)/A), with A = d'·d', ℓ* = −(o'·d')/A and
    p = o' + ℓ* d': the textbook discriminant B² − AC (B = o'·d') subtracts two numbers of size
    |o'|² A to get one of size A (1 − |p|²), and loses every digit of a grazing ray in float32
    once the primitive is a few radii away (Haines et al., Ray Tracing Gems ch. 7)."""
    a = (d_ell * d_ell).sum(-1)
    l_mid = -(o_ell * d_ell).sum(-1) / a
    closest = o_ell + l_mid[..., None] * d_ell
    h = (closest * closest).sum(-1)
    hit = h < 1.0
    half = torch.sqrt(torch.where(hit, (1.0 - h) / a, torch.ones_like(h)))  # where-guard: no NaN gradients
    return l_mid - half, l_mid + half, hit


def sinc(x: torch.Tensor) -> torch.Tensor:
    """Unnormalised sinc, sin(x)/x (torch.sinc is the normalised sin(πx)/(πx), and slow on the
    CPU). sin(x)/x is accurate in floating point down to the smallest normal x; only x = 0 itself
    (a zero-length chord, or a ray exactly perpendicular to a frequency) needs its limit, 1."""
    return torch.nan_to_num(torch.sin(x) / x, nan=1.0)


def _sinc_differentiable(x: torch.Tensor) -> torch.Tensor:
    """sinc for autograd: sin(x)/x has a 0/0 gradient at x = 0, where its limit's is 0."""
    zero = x == 0
    safe = torch.where(zero, torch.ones_like(x), x)
    return torch.where(zero, torch.ones_like(x), torch.sin(safe) / safe)


def _sinc_slope(x: torch.Tensor, cos_x: torch.Tensor, sinc_x: torch.Tensor) -> torch.Tensor:
    """d sinc/dx = (cos x − sinc x)/x, by its series −x/3 + x³/30 where the difference cancels."""
    small = x.abs() < 1e-2
    safe = torch.where(small, torch.ones_like(x), x)
    return torch.where(small, x * (x * x / 30.0 - 1.0 / 3.0), (cos_x - sinc_x) / safe)


def _sum_to(grad: torch.Tensor, shape: torch.Size) -> torch.Tensor:
    """Undo broadcasting: sum `grad` over the dimensions where `shape` has size 1."""
    dims = [i for i, (g, s) in enumerate(zip(grad.shape, shape)) if s == 1 and g != 1]
    return grad.sum(dims, keepdim=True) if dims else grad


class _CosMLPIntegral(torch.autograd.Function):
    """Σ_k W2_k Δ cos(a_k τ_m + c_k) sinc(a_k Δ / 2) over the last dim (N), with a hand-written
    backward. When gradients are wanted the forward also keeps sin φ and sinc's slope, so a
    training step evaluates 4 transcendentals per (pair, unit) instead of autograd's 6 and none of
    its dozen stored intermediates: about half the time and memory of the backward pass."""

    @staticmethod
    def forward(ctx, a, c, w2, tau_m, delta):
        d = delta[..., None]
        phase = a * tau_m[..., None] + c
        x = 0.5 * a * d
        sin_x = torch.sin(x)
        sinc_x = torch.nan_to_num(sin_x / x, nan=1.0)
        cos_p = torch.cos(phase)
        if any(ctx.needs_input_grad):
            slope = _sinc_slope(x, torch.cos(x), sinc_x)
            ctx.save_for_backward(a, c, w2, tau_m, delta, cos_p, torch.sin(phase), sinc_x, slope)
        return (w2 * d * cos_p * sinc_x).sum(-1)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        a, c, w2, tau_m, delta, cos_p, sin_p, s, slope = ctx.saved_tensors
        d, g = delta[..., None], grad[..., None]
        gwd = g * w2 * d
        g_phase = -gwd * sin_p * s            # ∂/∂(a τ_m + c)
        g_x = gwd * cos_p * slope             # ∂/∂(a Δ / 2)
        grad_a = g_phase * tau_m[..., None] + 0.5 * g_x * d
        grad_tau = (g_phase * a).sum(-1)
        cos_s = cos_p * s
        grad_delta = (g * w2 * cos_s + 0.5 * g_x * a).sum(-1)
        return grad_a, _sum_to(g_phase, c.shape), _sum_to(g * d * cos_s, w2.shape), grad_tau, grad_delta


def neural_optical_depth(l_in, l_out, hit, a, c, w2, b2, inv_smax) -> torch.Tensor:
    """Closed-form line integral of the cos-MLP density (paper eq. 7-8, stable sinc form).

    With τ = ℓ / max(s) (optical depth in units of the primitive's size, as the authors' kernel),
    Δ = τ_out − τ_in, τ_m = (τ_in + τ_out)/2, a_k = ω0 W1_k·d̂ and c_k = ω0 (W1_k·u0 + b1_k):
        I = Σ_k W2_k Δ cos(a_k τ_m + c_k) sinc(a_k Δ / 2) + b2 Δ,
    which is S(τ_out) − S(τ_in) rewritten with sin A − sin B = 2 cos((A+B)/2) sin((A−B)/2), so
    it never divides by a_k. Shapes: l_in, l_out, hit, b2, inv_smax (...,); a, c, w2 (..., N).
    """
    delta = torch.clamp_min(l_out - l_in, 0.0) * inv_smax
    tau_m = 0.5 * (l_in + l_out) * inv_smax
    integral = _CosMLPIntegral.apply(a, c, w2, tau_m, delta) + b2 * delta
    return torch.where(hit, integral, torch.zeros_like(integral))


def _below_one(x, series, formula):
    """series(x) where |x| < 1 (where the formula cancels), formula(x) elsewhere."""
    small = x.abs() < 1.0
    return torch.where(small, series(x), formula(torch.where(small, torch.ones_like(x), x)))


def window_integral(x: torch.Tensor) -> torch.Tensor:
    """W(x) = ½ ∫_{−1}^{1} (1 − t²) cos(x t) dt = 2 (sin x − x cos x) / x³, the windowed twin of
    sinc (sinc x = ½ ∫ cos(x t) dt), by its series 2/3 − x²/15 + x⁴/420 − … below |x| = 1."""
    def series(x):
        x2 = x * x
        return 2 / 3 - x2 * (1 / 15 - x2 * (1 / 420 - x2 * (1 / 22680 - x2 * (1 / 1995840 - x2 / 259459200))))
    return _below_one(x, series, lambda x: 2 * (torch.sin(x) - x * torch.cos(x)) / (x * x * x))


def windowed_optical_depth(l_in_raw, l_in, l_out, hit, a_sq, a, c, w2, b2, inv_smax) -> torch.Tensor:
    """Closed-form line integral of the windowed density 1.5 (1 − r²) σ (primitives.density_window).

    Along the ray, r² = |p|² + A (ℓ − ℓ*)² (ray_ellipsoid), so in τ = ℓ / max(s) about the clipped
    chord's midpoint τ_m, with half-length h = Δ/2, s = τ − τ_m and the near-plane clip
    e = τ_in − τ_in,unclipped ≥ 0: 1 − r² = κ (h + e + s)(h − s), κ = A max(s)². With
    φ_k = a_k τ_m + c_k, x_k = a_k Δ/2 and ½∫(1 − t²) cos(x t) dt = W (window_integral):
        I = 1.5 κ [Σ_k W2_k (cos φ_k Δ³/4 W(x_k) + e Δ²/2 (cos φ_k sinc x_k + sin φ_k x_k W(x_k)/2))
                   + b2 (Δ³/6 + e Δ²/2)],
    the e terms vanishing where no near plane cuts the chord. Shapes as neural_optical_depth,
    plus l_in_raw (the unclipped entry) and a_sq = A = |S⁻¹Rᵀ d̂|² (...,)."""
    delta = torch.clamp_min(l_out - l_in, 0.0) * inv_smax
    tau_m = 0.5 * (l_in + l_out) * inv_smax
    clip = (l_in - l_in_raw) * inv_smax
    kappa = a_sq / (inv_smax * inv_smax)
    d2, e = (0.5 * delta * delta)[..., None], clip[..., None]
    d3 = (0.25 * delta * delta * delta)[..., None]
    x = 0.5 * a * delta[..., None]
    phase = a * tau_m[..., None] + c
    cos_p, w = torch.cos(phase), window_integral(x)
    terms = cos_p * d3 * w + e * d2 * (cos_p * _sinc_differentiable(x) + torch.sin(phase) * (0.5 * x * w))
    inner = (w2 * terms).sum(-1) + b2 * (delta * delta * delta / 6.0 + clip * (0.5 * delta * delta))
    integral = WINDOW_GAIN * kappa * inner
    return torch.where(hit, integral, torch.zeros_like(integral))


def alpha_from_optical_depth(optical_depth: torch.Tensor) -> torch.Tensor:
    """Paper eq. 9, α = 1 − exp(−max(0, I)), with the 3DGS clamp α ≤ 0.99 and skip below 1/255."""
    alpha = torch.clamp_max(-torch.expm1(-torch.clamp_min(optical_depth, 0.0)), ALPHA_MAX)
    return torch.where(alpha < ALPHA_MIN, torch.zeros_like(alpha), alpha)


def gaussian_alpha(dx, dy, conic, opacity) -> torch.Tensor:
    """EWA splat weight of a pixel offset (dx, dy) from the projected mean, with conic (a, b, c) =
    inverse 2D covariance entries (..., 3) and opacity in (0, 1)."""
    power = -0.5 * (conic[..., 0] * dx * dx + conic[..., 2] * dy * dy) - conic[..., 1] * dx * dy
    alpha = torch.clamp_max(opacity * torch.exp(torch.clamp_max(power, 0.0)), ALPHA_MAX)
    return torch.where((alpha < ALPHA_MIN) | (power > 0), torch.zeros_like(alpha), alpha)
