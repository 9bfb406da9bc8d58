"""The Gaussian's torch twin per view and per pair: EWA splatting (Zwicker et al., as in 3DGS), the
3σ pixel bounds, and α of splats over blocks of image points."""

from __future__ import annotations


import torch

from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.core.splat.kernels import gaussian_alpha
from radfield.core.splat.view import clip_bounds



EWA_BLUR = 0.3          # 3DGS low-pass filter added to the 2D covariance (pixels²)


def jacobian_clamp(camera) -> tuple[float, float, float, float]:
    """(lo_x, hi_x, lo_y, hi_y): as 3DGS/gsplat, the EWA Jacobian's point x/z, y/z is clamped to 1.3×
    the field of view, which keeps the affine approximation of far off-screen splats from exploding."""
    margin_x, margin_y = 0.15 * camera.width / camera.fx, 0.15 * camera.height / camera.fy
    return (-camera.cx / camera.fx - margin_x, (camera.width - camera.cx) / camera.fx + margin_x,
            -camera.cy / camera.fy - margin_y, (camera.height - camera.cy) / camera.fy + margin_y)


def ewa_view(prims, camera, w2c, means_cam, near):
    """EWA splatting (Zwicker et al., as in 3DGS): ((2D mean, conic of J W Σ Wᵀ Jᵀ + 0.3 I,
    opacity), the 2D covariance's entries (a, b, c))."""
    x, y, z = means_cam.unbind(-1)
    zs = torch.where(z > near, z, torch.ones_like(z))
    lo_x, hi_x, lo_y, hi_y = jacobian_clamp(camera)
    tx = zs * torch.clamp(x / zs, lo_x, hi_x)
    ty = zs * torch.clamp(y / zs, lo_y, hi_y)
    zero = torch.zeros_like(zs)
    jac = torch.stack([camera.fx / zs, zero, -camera.fx * tx / zs**2,
                       zero, camera.fy / zs, -camera.fy * ty / zs**2], -1).reshape(-1, 2, 3)
    rot = w2c[:3, :3] @ quat_to_rotmat(prims.quats)
    rs = rot * torch.exp(prims.log_scales)[:, None, :]
    t = jac @ rs
    cov = t @ t.transpose(1, 2)
    a, b, c = cov[:, 0, 0] + EWA_BLUR, cov[:, 0, 1], cov[:, 1, 1] + EWA_BLUR
    det = a * c - b * b
    conic = torch.stack([c, -b, a], -1) / det[:, None]
    mean2d = torch.stack([camera.fx * x / zs + camera.cx, camera.fy * y / zs + camera.cy], -1)
    return (mean2d, conic, torch.sigmoid(prims.opacities)), (a, b, c)


@torch.no_grad()
def splat_bounds(mean2d, a, b, c, depth, camera, near):
    """The 3σ pixel box of each splat (largest eigenvalue of its covariance (a, b, c)); visible
    when in front of the near plane with a positive-definite covariance and a box in the image."""
    det = a * c - b * b
    lam_max = 0.5 * (a + c) + torch.sqrt(torch.clamp_min(0.25 * (a - c) ** 2 + b * b, 0.0))
    radius = torch.ceil(3.0 * torch.sqrt(lam_max))
    cx, cy = mean2d[:, 0], mean2d[:, 1]
    box = torch.stack([torch.ceil(cx - radius - 0.5), torch.ceil(cy - radius - 0.5),
                       torch.floor(cx + radius - 0.5), torch.floor(cy + radius - 0.5)], -1)
    big = float(max(camera.width, camera.height) + 1)
    return clip_bounds(torch.nan_to_num(box, nan=-1.0).clamp(-big, big).long(), (depth > near) & (det > 0), camera)


def pair_alpha(u, v, intrinsics, mean2d, conic, opacity):
    """α of splats (P,) over blocks of image points (P, A)."""
    return gaussian_alpha(u - mean2d[:, None, 0], v - mean2d[:, None, 1], conic[:, None, :], opacity[:, None])
