"""The two primitive representations as plain containers of tensors.

NeuralPrimitives: ellipsoid-bounded cos-MLP density fields (Splat the Net, eq. 5-6).
Gaussians: 3D Gaussians as in 3DGS. Both share the geometry (means, log_scales, quats) and
the SH colour layout, so the renderer can bin and composite them identically.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import torch

from radfield.core.render.sh import num_sh_coeffs, sh_degree_from_coeffs

DEFAULT_OMEGA0 = 30.0
DEFAULT_HIDDEN = 8


WINDOW_GAIN = 1.5   # the window 1.5 (1 − r²): the central chord's optical depth is the hard-edged one's


def ellipsoid_radius_sq(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                        x: torch.Tensor) -> torch.Tensor:
    """r² = |S⁻¹Rᵀ(x − μ)|² (...,) of points x (..., 3) in the unit-sphere frame of the ellipsoids
    B(μ, R, s) (r² ≤ 1: inside); means, log_scales (..., 3) and quats (..., 4) broadcast against x.
    The one place the window's radius is computed (the point sites' hard inside tests keep their
    own |S⁻¹Rᵀ(x − μ)| ≤ 1, so a hard-edged model's results stay bit for bit)."""
    rot = quat_to_rotmat(quats)
    local = ((x - means)[..., None, :] @ rot)[..., 0, :] * torch.exp(-log_scales)   # Rᵀ(x − μ) / s
    return (local * local).sum(-1)


def density_window(prims: "NeuralPrimitives", r2: torch.Tensor) -> torch.Tensor | float:
    """The factor on σ at points of squared ellipsoid radius r2 = |S⁻¹Rᵀ(x − μ)|² (inside: r2 ≤ 1):
    1.5 (1 − r2) for a windowed model, 1 for a hard-edged one. Every evaluation of a neural
    primitive's density at points takes it from here (the renderer integrates it in closed form)."""
    return WINDOW_GAIN * (1.0 - r2) if prims.window else 1.0


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (P, 3, 3) from quaternions (P, 4) in w x y z order (normalised here)."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(quats.shape[:-1] + (3, 3))


def rotmat_to_quat(rot: torch.Tensor) -> torch.Tensor:
    """Quaternions (P, 4, w x y z, w >= 0) from rotation matrices (P, 3, 3)."""
    m = rot
    t = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = torch.stack(
        [
            torch.stack([1 + t, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + 2 * m[..., 0, 0] - t, m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 + 2 * m[..., 1, 1] - t, m[..., 1, 2] + m[..., 2, 1]], -1),
            torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 + 2 * m[..., 2, 2] - t], -1),
        ],
        -2,
    )  # each row is 4*q*q_i for the largest component i; pick the best-conditioned one
    diag = torch.stack([1 + t, 1 + 2 * m[..., 0, 0] - t, 1 + 2 * m[..., 1, 1] - t, 1 + 2 * m[..., 2, 2] - t], -1)
    best = diag.argmax(-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    q = torch.nn.functional.normalize(q, dim=-1)
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0)


@dataclass
class _Primitives:
    means: torch.Tensor       # (P, 3) centres μ
    log_scales: torch.Tensor  # (P, 3) ℓ, scales s = exp(ℓ)
    quats: torch.Tensor       # (P, 4) rotation q, w x y z, need not be normalised
    sh: torch.Tensor          # (P, K, 3) SH coefficients, K = (degree+1)^2
    # rays per pixel side the model was trained with (render.supersample, core/render/antialias.py): every
    # render for a user draws each pixel as the mean of n × n rays; the model file's `supersample`
    # key (absent = 1). Keyword-only, so it follows the subclasses' fields; map/to/select keep it.
    supersample: int = field(default=1, kw_only=True)

    kind = "base"

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_coeffs(self.sh.shape[1])

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    def tensors(self) -> dict[str, torch.Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self) if isinstance(getattr(self, f.name), torch.Tensor)}

    def num_params(self) -> int:
        return sum(t.numel() for t in self.tensors().values())

    def map(self, fn) -> "_Primitives":
        """A copy with `fn` applied to every tensor (e.g. `lambda t: t.to(device)`)."""
        return replace(self, **{k: fn(v) for k, v in self.tensors().items()})

    def to(self, device=None, dtype=None) -> "_Primitives":
        return self.map(lambda t: t.to(device=device, dtype=dtype))

    def select(self, index) -> "_Primitives":
        return self.map(lambda t: t[index])


@dataclass
class NeuralPrimitives(_Primitives):
    """Splattable neural primitives. Density inside the ellipsoid (radii s, paper eq. 5-6):
    σ(x) = w2 · cos(ω0 (w1 u + b1)) + b2,  u = (x − μ) / max(s), times the window 1.5 (1 − r²)
    where `window` is set (`density_window`)."""

    w1: torch.Tensor = None  # (P, N, 3)
    b1: torch.Tensor = None  # (P, N)
    w2: torch.Tensor = None  # (P, N)
    b2: torch.Tensor = None  # (P,)
    omega0: float = DEFAULT_OMEGA0
    # optional, written by `radfield edit --preserve-opacity` (edit/deform.py): per primitive the
    # symmetric rest-space metric G (xx yy zz xy xz yz) that scales the optical depth by √(d̂ᵀ G d̂)
    rest_metric: torch.Tensor | None = None  # (P, 6)
    # the density window (render.window, core/render/kernels.py: windowed_optical_depth): σ(x) is taken
    # times 1.5 (1 − r²), r = |S⁻¹Rᵀ(x − μ)|, so it falls to 0 on the ellipsoid and a primitive's
    # silhouette is smooth; False: the paper's hard-edged ellipsoid. The model file's `window` key
    # (absent = False); map/to/select keep it.
    window: bool = field(default=False, kw_only=True)

    kind = "neural"

    @property
    def hidden(self) -> int:
        return self.w1.shape[1]


@dataclass
class Gaussians(_Primitives):
    """3D Gaussians (3DGS): covariance R diag(s²) Rᵀ, opacity sigmoid(opacities)."""

    opacities: torch.Tensor = None  # (P,) logits

    kind = "gaussian"


Primitives = NeuralPrimitives | Gaussians


def siren_mlp_init(num: int, hidden: int = DEFAULT_HIDDEN, omega0: float = DEFAULT_OMEGA0, generator=None, dtype=torch.float32,
                   w1_bound: float = 1 / 3):
    """MLP weights as in the paper (§3.3, after SIREN): W1 ~ U(−1/3, 1/3), W2 ~ U(±√(6/N)/ω0), b1 ~ U(−1/3, 1/3).
    `w1_bound` replaces W1's 1/3: the initial frequency scale (each cosine starts at most
    ω0 · w1_bound · √3 rad per unit of u).

    b2 is returned as zeros; callers set it to the opacity level they want (see `density_offset_for_alpha`)."""
    u = lambda *shape: torch.rand(*shape, generator=generator, dtype=dtype) * 2 - 1
    w1 = u(num, hidden, 3) * w1_bound
    b1 = u(num, hidden) / 3
    w2 = u(num, hidden) * math.sqrt(6 / hidden) / omega0
    return w1, b1, w2, torch.zeros(num, dtype=dtype)


def random_neural(num: int, *, sh_degree: int = 0, hidden: int = DEFAULT_HIDDEN, omega0: float = DEFAULT_OMEGA0,
                  extent: float = 1.0, scale: float = 0.1, b2: float = 1.0, w2_amplitude: float = 0.3,
                  seed: int = 0, dtype=torch.float32) -> NeuralPrimitives:
    """Random primitives in a cube of half-size `extent` (for tests and benchmarks). W2 is drawn
    from U(±w2_amplitude), larger than the training init, so the cos terms visibly shape density."""
    g = torch.Generator().manual_seed(seed)
    w1, b1, _, _ = siren_mlp_init(num, hidden, omega0, g, dtype)
    return NeuralPrimitives(
        means=(torch.rand(num, 3, generator=g, dtype=dtype) * 2 - 1) * extent,
        log_scales=torch.log(scale * (0.5 + torch.rand(num, 3, generator=g, dtype=dtype))),
        quats=torch.randn(num, 4, generator=g, dtype=dtype),
        sh=torch.randn(num, num_sh_coeffs(sh_degree), 3, generator=g, dtype=dtype) * 0.5,
        w1=w1, b1=b1, w2=(torch.rand(num, hidden, generator=g, dtype=dtype) * 2 - 1) * w2_amplitude,
        b2=torch.full((num,), b2, dtype=dtype), omega0=omega0,
    )


def random_gaussians(num: int, *, sh_degree: int = 0, extent: float = 1.0, scale: float = 0.1, seed: int = 0,
                     dtype=torch.float32) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=(torch.rand(num, 3, generator=g, dtype=dtype) * 2 - 1) * extent,
        log_scales=torch.log(scale * (0.5 + torch.rand(num, 3, generator=g, dtype=dtype))),
        quats=torch.randn(num, 4, generator=g, dtype=dtype),
        sh=torch.randn(num, num_sh_coeffs(sh_degree), 3, generator=g, dtype=dtype) * 0.5,
        opacities=torch.randn(num, generator=g, dtype=dtype),
    )
