"""The neural primitive's torch twin per view and per pair: the frame M = S⁻¹Rᵀ and the MLP phases
a view shares, (W2, b2) as the pair kernels see them, and α of primitives over blocks of image
points (paper eq. 7-9; kernels.py has the line integral)."""

from __future__ import annotations


import torch

from radfield.core.splat.kernels import (alpha_from_optical_depth, ellipsoid_frame, neural_optical_depth, ray_ellipsoid,
                                         windowed_optical_depth)
from radfield.core.splat.view import camera_directions



def view_tensors(prims, campos: torch.Tensor, cam_rot: torch.Tensor) -> tuple:
    """What depends only on the primitive and the camera, computed once per view:
    M = S⁻¹Rᵀ, o' = M(o − μ), c_k = ω0 (W1_k·u0 + b1_k) with u0 = (o − μ)/max(s); and, because a
    pair's world direction is d̂ = R_cam d_cam/|d_cam|, the per-pair products M d̂ and ω0 W1 d̂
    become M R_cam and ω0 W1 R_cam applied to the camera-space pixel direction."""
    m, smax = ellipsoid_frame(prims.means, prims.log_scales, prims.quats)
    rel = campos - prims.means
    o_ell = (m * rel[:, None, :]).sum(-1)
    w = prims.omega0 * prims.w1
    c = (w * (rel / smax[:, None])[:, None, :]).sum(-1) + prims.omega0 * prims.b1
    w2, b2 = density_weights(prims, rel)
    return m @ cam_rot, o_ell, w @ cam_rot, c, w2, b2, 1.0 / smax


def density_weights(prims, rel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(W2, b2) as the pair kernels see them in this view (rel = o − μ); both the torch twin and
    the fused path (whose fused op computes the rest of `view_tensors`) take them from here."""
    w2, b2 = prims.w2, prims.b2
    if prims.rest_metric is not None:
        # preserve_opacity edits (edit/affine.py): optical depth in rest-space distance,
        # I·√(d̂ᵀGd̂); I is linear in (w2, b2), so the factor at the central ray d̂ = (μ − o)/|μ − o|
        # folds into them once per view (exact on that ray, docs/usage.md "Editing")
        g, d = prims.rest_metric, torch.nn.functional.normalize(-rel, dim=-1)
        quad = (g[:, :3] * d * d).sum(-1) + 2 * (g[:, 3] * d[:, 0] * d[:, 1] + g[:, 4] * d[:, 0] * d[:, 2] + g[:, 5] * d[:, 1] * d[:, 2])
        factor = torch.sqrt(torch.clamp_min(quad, 0.0))
        w2, b2 = w2 * factor[:, None], b2 * factor
    return w2, b2


def pair_alpha(u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax, window: bool = False):
    """α of primitives (P,) over blocks of image points (P, A) (paper eq. 7-9); `window`: the windowed density."""
    d, l_near = camera_directions(u, v, intrinsics)
    d_ell = d @ m_cam.transpose(1, 2)                    # d' = S⁻¹Rᵀ d̂
    l_in_raw, l_out, hit = ray_ellipsoid(o_ell[:, None, :], d_ell)
    l_in = torch.maximum(l_in_raw, l_near)               # camera inside: start at the near plane
    a = d @ w_cam.transpose(1, 2)                        # a_k = ω0 W1_k · d̂
    mlp = c[:, None, :], w2[:, None, :], b2[:, None], inv_smax[:, None]
    if window:
        optical_depth = windowed_optical_depth(l_in_raw, l_in, l_out, hit, (d_ell * d_ell).sum(-1), a, *mlp)
    else:
        optical_depth = neural_optical_depth(l_in, l_out, hit, a, *mlp)
    return alpha_from_optical_depth(optical_depth)
