"""What every view needs before its pairs are evaluated: the view's frame of numbers, the unit
rays through image points, and the pixel bounds of an ellipsoid from its dual conic."""

from __future__ import annotations

from typing import NamedTuple

import torch

from radfield.core.geometry.cameras import Camera
from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.util.transfer import to_device


class ViewFrame(NamedTuple):
    """One view as the renderer has prepared it for every kind (core/render/rasterize.py: render),
    in the primitives' dtype and device: the camera, its camera-to-world and world-to-camera
    matrices (4, 4), its centre (3,), the primitives' camera-space centres (P, 3) and depths (P,),
    the intrinsics tensor (fx, fy, cx, cy, near) the pair kernels read, and the near plane."""

    camera: "Camera"
    c2w: torch.Tensor
    w2c: torch.Tensor
    campos: torch.Tensor
    means_cam: torch.Tensor
    depth: torch.Tensor
    intrinsics: torch.Tensor
    near: float


def ellipsoid_bounds(prims, frame: ViewFrame) -> tuple[torch.Tensor, torch.Tensor]:
    """Tight pixel bounds of each projected bounding ellipsoid B(μ, R, s), from its dual conic
    C* = K (μμᵀ − Σ) Kᵀ (camera frame, Σ = R S² Rᵀ), and visibility. An ellipsoid that straddles
    the near plane gets the whole image (the pair kernel clips rays at the near plane itself)."""
    camera, means_cam, near = frame.camera, frame.means_cam, frame.near
    with torch.no_grad():
        rot = frame.w2c[:3, :3] @ quat_to_rotmat(prims.quats)
        rs = rot * torch.exp(prims.log_scales)[:, None, :]
        sigma = rs @ rs.transpose(1, 2)
        z_ext = torch.sqrt(sigma[:, 2, 2])
        z = means_cam[:, 2]
        in_front = z - z_ext > near
        visible = z + z_ext > near
        k = to_device(camera.K, means_cam.device, means_cam.dtype)
        dual = k @ (means_cam[:, :, None] * means_cam[:, None, :] - sigma) @ k.T
        box = conic_box(dual, camera.width, camera.height)
        # a primitive the near plane cuts: the whole image
        full = (0, 0, camera.width - 1, camera.height - 1)
        bounds = torch.stack([torch.where(in_front, side, edge) for side, edge in zip(box.unbind(-1), full)], -1)
        return clip_bounds(bounds, visible, camera)


def conic_box(dual: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Integer pixel bounds (x0, y0, x1, y1) of the points inside a conic, from its dual: the tangent
    lines u = const solve C*_00 − 2u C*_02 + u² C*_22 = 0 (likewise for v)."""
    def extent(i):
        c_ii, c_i2, c_22 = dual[:, i, i], dual[:, i, 2], dual[:, 2, 2]
        root = torch.sqrt(torch.clamp_min(c_i2 * c_i2 - c_ii * c_22, 0.0))
        lo, hi = (c_i2 + root) / c_22, (c_i2 - root) / c_22
        return torch.minimum(lo, hi), torch.maximum(lo, hi)

    (u0, u1), (v0, v1) = extent(0), extent(1)
    # pixel j covers centre j + 0.5: first/last centres inside [u0, u1]
    box = torch.stack([torch.ceil(u0 - 0.5), torch.ceil(v0 - 0.5), torch.floor(u1 - 0.5), torch.floor(v1 - 0.5)], -1)
    big = float(max(width, height) + 1)
    return torch.nan_to_num(box, nan=-1.0).clamp(-big, big).long()


def clip_bounds(bounds: torch.Tensor, visible: torch.Tensor, camera) -> tuple[torch.Tensor, torch.Tensor]:
    """Boxes clipped to the image, and visibility without the boxes left empty."""
    x0, y0 = bounds[:, 0].clamp_min(0), bounds[:, 1].clamp_min(0)
    x1, y1 = bounds[:, 2].clamp_max(camera.width - 1), bounds[:, 3].clamp_max(camera.height - 1)
    visible = visible & (x1 >= x0) & (y1 >= y0)
    return torch.stack([x0, y0, x1, y1], -1), visible


def camera_directions(u: torch.Tensor, v: torch.Tensor, intrinsics: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit camera-space directions (P, A, 3) through image points (u, v) (P, A), and the ray
    distance of the near plane along each."""
    fx, fy, cx, cy, near = intrinsics.unbind()
    d = torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], -1)
    norm = torch.linalg.vector_norm(d, dim=-1)
    return d / norm[..., None], near * norm
