"""Non-negative density for neural primitives: a projection that keeps σ(x) ≥ 0 everywhere.

A neural primitive's density (Splat the Net eq. 5) σ(x) = Σ_n W2_n cos(ω0 (W1_n · u + b1_n)) + b2
is a signed field: only the line integral is clamped, α = 1 − exp(−max(0, I)) (eq. 9). A trained
primitive can therefore hold regions of negative density that cancel positive ones along some rays
and not along others — a freedom no physical volume has, and one few, nearly co-directional
training views do not constrain (each photo gets its own pattern of cancellations;
docs/studies/few-view-captures.md: on fox_small and fern 99.9 % of the trained primitives have b2 < ‖W2‖₁, i.e.
can go negative). Eq. 6 bounds the density from below,

    σ(x) ≥ b2 − ‖W2‖₁                                                                          (1)

so the convex cone C = {(W2, b2): ‖W2‖₁ ≤ b2} holds only primitives whose density is non-negative
at every point, windowed or not (the window 1.5 (1 − r²) of prims.window is ≥ 0 inside the
ellipsoid). After every optimiser step (`train.nonnegative_density`) each primitive's (W2, b2)
is replaced by its Euclidean projection onto C (projected Adam, as the frequency cap). The
projection's optimality conditions give

    W2' = S_λ(W2) (soft-thresholding: sign(w) max(|w| − λ, 0)),   b2' = b2 + λ,                 (2)

with λ ≥ 0 the root of g(λ) = ‖S_λ(W2)‖₁ − b2 − λ, which decreases strictly in λ; λ = 0 when
(W2, b2) is in C already, to rounding (unchanged, bit for bit), and (0, 0) when b2 ≤ −max|W2| (the polar cone:
no density left; population control prunes it as negligible). g is piecewise linear, so the root
is found exactly: over the sorted |W2| (descending, a_1 ≥ … ≥ a_N) with m units above λ,
λ = (Σ_{i≤m} a_i − b2) / (m + 1), for the m with a_{m+1} ≤ λ < a_m.

Where it applies (`train.nonnegative_density` = θ, degrees): the signed freedom matters when the
views that constrain a primitive are nearly co-directional — all its line integrals then run
through it in nearly one direction, and cancellations fit each photo without being seen from
anywhere else. Per primitive, the training views that see it (its bounding sphere meets their
frustum) give unit directions d_c from the centre to the camera centres; with m their normalised
mean, the half-angle of its view cone is

    β = max_c ∠(d_c, m)                                                                        (3)

and the projection applies to the primitives with β < θ (θ = 180: every primitive; 0: off). On
the study's captures β's median is 9° on fern (forward-facing), 48° on fox_small and 92° on
lego_small (docs/studies/few-view-captures.md). β depends on the means and scales, so it is recomputed
at the steps the frequency cap refreshes its bound (every gcd(densify.every, checkpoint_every)
steps, radfield.core.train.strategy.refresh_interval: after every change of the population): a resumed run recomputes the mask
the uninterrupted run used.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from radfield.core import backends
from radfield.core.geometry.cameras import Camera
from radfield.core.train.strategy import in_frustum, refresh_interval, stale


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


def view_cone_half_angle(means: torch.Tensor, radius: torch.Tensor, cameras: Sequence[Camera],
                         near: float) -> torch.Tensor:
    """β of eq. (3) in degrees (P,): the half-angle of the cone of directions from each centre to
    the training cameras whose frustum its sphere of `radius` meets (0 when fewer than two do)."""
    total = torch.zeros_like(means)
    seen = []
    for camera in cameras:
        visible = in_frustum(means, radius, camera, near)
        direction = torch.nn.functional.normalize(camera.center.to(means) - means, dim=-1)
        total += torch.where(visible[:, None], direction, 0.0)
        seen.append(visible)
    mean = torch.nn.functional.normalize(total, dim=-1)
    cos = torch.ones_like(radius)
    for camera, visible in zip(cameras, seen):
        direction = torch.nn.functional.normalize(camera.center.to(means) - means, dim=-1)
        cos = torch.where(visible, torch.minimum(cos, (direction * mean).sum(-1)), cos)
    return torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0)))


class NonNegativeDensity:
    """`apply(params, step)` after each optimiser step: (W2, b2) onto C (in place) for the
    primitives whose view cone is narrower than θ (eq. 3; θ ≥ 180: every primitive)."""

    def __init__(self, cameras: Sequence[Camera], *, threshold: float, near: float, every: int = 100):
        if not 0 <= threshold <= 180:
            raise ValueError(f"view-cone threshold must be in [0, 180] degrees, got {threshold}")
        self.cameras = list(cameras)
        self.threshold = threshold
        self.near = near
        self.every = max(int(every), 1)
        self._mask = None  # (P,) bool: the primitives projected
        self._rows = None  # their row numbers, found with the mask (not every step: on a GPU a read waits)

    @classmethod
    def for_training(cls, cameras: Sequence[Camera], cfg: dict, *, near: float) -> "NonNegativeDensity":
        """The rule of a training run from its `train` section (the neural kind's training rule,
        radfield.core.kinds.neural); refreshed at the steps the frequency cap refreshes
        (radfield.core.train.frequency.FrequencyCap.for_training)."""
        every = refresh_interval(cfg)
        return cls(cameras, threshold=cfg["nonnegative_density"], near=near, every=every)

    @property
    def enabled(self) -> bool:
        return self.threshold > 0

    def mask(self, params: dict[str, torch.Tensor]) -> torch.Tensor:
        means = params["means"].detach()
        if self.threshold >= 180:
            return torch.ones(means.shape[0], dtype=torch.bool, device=means.device)
        radius = torch.exp(params["log_scales"].detach().amax(-1))
        return view_cone_half_angle(means, radius, self.cameras, self.near) < self.threshold

    @torch.no_grad()
    def apply(self, params: dict[str, torch.Tensor], step: int) -> None:
        if not self.enabled:
            return
        if stale(self._mask, params["w2"].shape[0], step, self.every):
            self._mask = self.mask(params)
            self._rows = self._mask.nonzero()[:, 0]  # rows are projected independently: only these change
        if not len(self._rows):
            return  # object-centric captures: no primitive has a narrow cone, nothing to do
        w2, b2 = params["w2"], params["b2"]
        fast = backends.kernel(backends.Op.PROJECT_NONNEGATIVE, w2.device, w2.dtype)
        if fast is not None and w2.is_contiguous() and b2.is_contiguous() and b2.dtype == w2.dtype:
            fast(w2, b2, self._mask)   # one pass over the masked rows (fused: core/backends/csrc/positivity_kernels.cpp)
            return
        rows = self._rows
        w2, b2 = project_nonnegative(params["w2"][rows], params["b2"][rows])
        params["w2"][rows] = w2
        params["b2"][rows] = b2
