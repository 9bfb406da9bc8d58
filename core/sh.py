"""Real spherical harmonics up to degree 3, in the coefficient order and sign convention of 3DGS."""

from __future__ import annotations

import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def num_sh_coeffs(degree: int) -> int:
    return (degree + 1) ** 2


def sh_degree_from_coeffs(k: int) -> int:
    degree = round(k**0.5) - 1
    if num_sh_coeffs(degree) != k or not 0 <= degree <= 3:
        raise ValueError(f"{k} SH coefficients is not (degree+1)^2 for a degree in 0..3")
    return degree


def eval_sh(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """SH radiance for coefficients (P, K, 3) along unit directions (P, 3), using bands <= degree.

    Returns the raw value (P, 3); colour = clamp(value + 0.5, min=0) as in 3DGS."""
    x, y, z = dirs.unbind(-1)
    basis = [torch.full_like(x, C0)]
    if degree >= 1:
        basis += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        basis += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy)]
    if degree >= 3:
        basis += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * x * y * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    basis = torch.stack(basis, -1)  # (P, B)
    return (basis[..., None] * coeffs[:, : basis.shape[-1]]).sum(-2)


def sh_to_color(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """3DGS colour convention: SH value + 0.5, clamped at 0 (no upper clamp)."""
    return torch.clamp_min(eval_sh(coeffs, dirs, degree) + 0.5, 0.0)


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient that reproduces a colour (inverse of the degree-0 path)."""
    return (rgb - 0.5) / C0
