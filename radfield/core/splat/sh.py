"""Real spherical harmonics up to degree 3, in the coefficient order and sign convention of 3DGS."""

from __future__ import annotations

import math

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


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """The real SH basis functions (..., (degree+1)^2) at unit directions (..., 3), 3DGS order and signs."""
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
    return torch.stack(basis, -1)


def eval_sh(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """SH radiance for coefficients (P, K, 3) along unit directions (P, 3), using bands <= degree.

    Returns the raw value (P, 3); colour = clamp(value + 0.5, min=0) as in 3DGS."""
    basis = sh_basis(dirs, degree)  # (P, B)
    return (basis[..., None] * coeffs[:, : basis.shape[-1]]).sum(-2)


def fibonacci_sphere(n: int) -> torch.Tensor:
    """n near-uniform unit directions (n, 3), float64 (the Fibonacci sphere)."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    r = torch.sqrt(1.0 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def rotate_sh(coeffs: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
    """SH coefficients (P, K, 3) of the rotated functions: with c' = rotate_sh(c, R),
    eval_sh(c', d) = eval_sh(c, Rᵀd) for every unit d (colour turns with an object rotated by R).

    Each band l spans a rotation-invariant space, so band by band c'_l = D_l(R) c_l with the
    (2l+1)² matrix D_l fitted exactly on fixed directions P: D_l = pinv(Y_l(P)) Y_l(Rᵀ P) (a
    least-squares fit of a function that lies in the span, exact to rounding). This matches
    `sh_basis`'s order and signs by construction, whatever convention it uses. rot: (P, 3, 3) or (3, 3)."""
    degree = sh_degree_from_coeffs(coeffs.shape[1])
    if degree == 0:
        return coeffs.clone()
    dtype = coeffs.dtype
    rot = torch.as_tensor(rot, dtype=torch.float64, device=coeffs.device).expand(coeffs.shape[0], 3, 3)
    dirs = fibonacci_sphere(32).to(coeffs.device)                     # 32 >= 2l+1 for every band
    rest = dirs @ rot                                                  # rows Rᵀ p  (P, 32, 3)
    y_fixed, y_rot = sh_basis(dirs, degree), sh_basis(rest, degree)    # (32, K), (P, 32, K)
    out = coeffs.to(torch.float64).clone()
    for band in range(1, degree + 1):
        lo, hi = band * band, (band + 1) * (band + 1)
        d = torch.linalg.pinv(y_fixed[:, lo:hi]) @ y_rot[..., lo:hi]  # (P, 2l+1, 2l+1)
        out[:, lo:hi] = d @ out[:, lo:hi]
    return out.to(dtype)


def join_sh(sh_dc: torch.Tensor, sh_rest: torch.Tensor) -> torch.Tensor:
    """The coefficients (P, K, 3) = cat([sh_dc (P, 1, 3), sh_rest (P, K − 1, 3)], 1), as the
    trainer assembles them from its two parameters. The result remembers its two parts
    (`sh_parts`): the fused CPU renderer evaluates the colour from them directly
    (fused.sh_color_parts), so on that path the concatenation is no part of the colour's autograd
    graph and its backward (two copies of the gradient) never runs. Any other use of the tensor
    differentiates through the concatenation as usual; copies of it (`.detach()`, `.to()`) are
    plain tensors."""
    sh = torch.cat([sh_dc, sh_rest], 1)
    sh.sh_parts = (sh_dc, sh_rest)
    return sh


def sh_parts(sh: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The (sh_dc, sh_rest) that `join_sh` concatenated into `sh`, or None."""
    return getattr(sh, "sh_parts", None)


def sh_to_color(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """3DGS colour convention: SH value + 0.5, clamped at 0 (no upper clamp)."""
    return torch.clamp_min(eval_sh(coeffs, dirs, degree) + 0.5, 0.0)


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient that reproduces a colour (inverse of the degree-0 path)."""
    return (rgb - 0.5) / C0
