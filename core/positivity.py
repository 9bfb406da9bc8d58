"""Non-negative density for neural primitives: a projection that keeps σ(x) ≥ 0 everywhere.

A neural primitive's density (Splat the Net eq. 5) σ(x) = Σ_n W2_n cos(ω0 (W1_n · u + b1_n)) + b2
is a signed field: only the line integral is clamped, α = 1 − exp(−max(0, I)) (eq. 9). A trained
primitive can therefore hold regions of negative density that cancel positive ones along some rays
and not along others — a freedom no physical volume has, and one few, nearly co-directional
training views do not constrain (each photo gets its own pattern of cancellations; README
"Few-view captures": on fox_small and fern 99.9 % of the trained primitives have b2 < ‖W2‖₁, i.e.
can go negative). Eq. 6 bounds the density from below,

    σ(x) ≥ b2 − ‖W2‖₁                                                                          (1)

so the convex cone C = {(W2, b2): ‖W2‖₁ ≤ b2} holds only primitives whose density is non-negative
at every point. After every optimiser step (`train.nonnegative_density`) each primitive's (W2, b2)
is replaced by its Euclidean projection onto C (projected Adam, as the frequency cap). The
projection's optimality conditions give

    W2' = S_λ(W2) (soft-thresholding: sign(w) max(|w| − λ, 0)),   b2' = b2 + λ,                 (2)

with λ ≥ 0 the root of g(λ) = ‖S_λ(W2)‖₁ − b2 − λ, which decreases strictly in λ; λ = 0 when
(W2, b2) is in C already, to rounding (unchanged, bit for bit), and (0, 0) when b2 ≤ −max|W2| (the polar cone:
no density left; population control prunes it as negligible). g is piecewise linear, so the root
is found exactly: over the sorted |W2| (descending, a_1 ≥ … ≥ a_N) with m units above λ,
λ = (Σ_{i≤m} a_i − b2) / (m + 1), for the m with a_{m+1} ≤ λ < a_m.
"""

from __future__ import annotations

import torch


def project_nonnegative(w2: torch.Tensor, b2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The Euclidean projection of each row (W2 (P, N), b2 (P,)) onto ‖W2‖₁ ≤ b2 (eq. 2)."""
    a = w2.abs().sort(dim=-1, descending=True).values                               # (P, N)
    m = torch.arange(1, a.shape[-1] + 1, dtype=a.dtype, device=a.device)
    lam = (a.cumsum(-1) - b2[:, None]) / (m + 1)                                   # λ if m units stay
    below = torch.cat([a[:, 1:], torch.zeros_like(a[:, :1])], -1)                  # a_{m+1}
    valid = (lam >= below) & (lam < a)
    # the first valid m (there is exactly one when λ > 0); none: the polar cone, everything to 0
    first = torch.where(valid.any(-1), valid.float().argmax(-1), a.shape[-1] - 1)
    lam = lam.gather(-1, first[:, None])[:, 0].clamp_min(0.0)
    # within rounding of the cone counts as inside, so a second projection changes nothing
    inside = w2.abs().sum(-1) <= b2 + 1e-6 * (b2.abs() + 1)
    polar = ~valid.any(-1) & ~inside
    new_w2 = torch.sign(w2) * (w2.abs() - lam[:, None]).clamp_min(0.0)
    new_b2 = torch.where(polar, torch.zeros_like(b2), b2 + lam)
    new_w2 = torch.where(polar[:, None], torch.zeros_like(w2), new_w2)
    return torch.where(inside[:, None], w2, new_w2), torch.where(inside, b2, new_b2)


class NonNegativeDensity:
    """`apply(params)` after each optimiser step: (W2, b2) of every primitive onto C (in place)."""

    def __init__(self, enabled: bool):
        self.enabled = bool(enabled)

    @classmethod
    def for_training(cls, cfg: dict, *, kind: str) -> "NonNegativeDensity":
        return cls(cfg["nonnegative_density"] and kind == "neural")

    @torch.no_grad()
    def apply(self, params: dict[str, torch.Tensor]) -> None:
        if not self.enabled:
            return
        w2, b2 = project_nonnegative(params["w2"], params["b2"])
        params["w2"].copy_(w2)
        params["b2"].copy_(b2)
