"""3D Gaussians (3DGS): the kind "gaussian".

Covariance R diag(s²) Rᵀ, opacity sigmoid(opacities), drawn by EWA splatting (Zwicker et al., as
in 3DGS). Everything the rest of radfield needs to know about the kind is said here (kinds/base.py
lists the hooks): its opacity parameter, its renderer hooks (EWA projection, 3σ bounds, the splat's
pair kernel and the fused CPU view), 3DGS's adaptive density control, its initialisation, and that
it exports as itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from radfield.core import backends
from radfield.core.backends import fused, gpu
from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.core.kinds.base import INITIAL_ALPHA, PrimitiveKind, ViewFrame, _Primitives, clip_bounds, register
from radfield.core.render.kernels import gaussian_alpha
from radfield.core.render.sh import num_sh_coeffs

EWA_BLUR = 0.3          # 3DGS low-pass filter added to the 2D covariance (pixels²)
INITIAL_OPACITY = math.log(INITIAL_ALPHA / (1.0 - INITIAL_ALPHA))  # logit of a new Gaussian's opacity, as 3DGS


@dataclass
class Gaussians(_Primitives):
    """3D Gaussians (3DGS): covariance R diag(s²) Rᵀ, opacity sigmoid(opacities)."""

    opacities: torch.Tensor = None  # (P,) logits

    kind = "gaussian"


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


# --- the torch twin's per-view preparation and pair kernel ---------------------------------------

def jacobian_clamp(camera) -> tuple[float, float, float, float]:
    """(lo_x, hi_x, lo_y, hi_y): as 3DGS/gsplat, the EWA Jacobian's point x/z, y/z is clamped to 1.3×
    the field of view, which keeps the affine approximation of far off-screen splats from exploding."""
    margin_x, margin_y = 0.15 * camera.width / camera.fx, 0.15 * camera.height / camera.fy
    return (-camera.cx / camera.fx - margin_x, (camera.width - camera.cx) / camera.fx + margin_x,
            -camera.cy / camera.fy - margin_y, (camera.height - camera.cy) / camera.fy + margin_y)


def ewa_view(prims: Gaussians, camera, w2c, means_cam, near):
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


def _fused_cpu_view(prims: Gaussians, frame: ViewFrame, colors: torch.Tensor, t_min: float):
    """The whole view on the fused CPU kernels: EWA projection, bounds and depth order, and the
    compositing in C++ (core/backends/csrc/prepare_kernels.cpp, view_kernels.cpp); returns
    (Σ w c, Σ w z, T, counters, the number of visible primitives)."""
    camera = frame.camera
    mean2d, conic, cov = fused.gaussian_prep(frame.means_cam, prims.log_scales, prims.quats, frame.w2c[:3, :3],
                                             frame.intrinsics, camera.width, camera.height, frame.near)
    view = (mean2d, conic, torch.sigmoid(prims.opacities))
    bounds, ids = fused.gaussian_bounds(mean2d, cov, frame.depth, camera.width, camera.height, frame.near)
    out = fused.gaussian_view(bounds, ids, camera.height, camera.width, t_min, colors, frame.depth, *view)
    return (*out, ids.numel())


class GaussianKind(PrimitiveKind):
    name = "gaussian"
    primitives = Gaussians
    own_params = {"opacities": ()}
    exact_gaussians = True
    bench_variants = ("gaussian",)

    def twin_view(self, prims, frame: ViewFrame):
        view, cov = ewa_view(prims, frame.camera, frame.w2c, frame.means_cam, frame.near)
        bounds, visible = splat_bounds(view[0], *cov, frame.depth, frame.camera, frame.near)
        return bounds, visible, view

    def pair_kernel(self, prims):
        return pair_alpha

    def reference_alpha(self, prims, i, ray, depth):
        from radfield.core.render.reference import gaussian_pixel_alpha

        if depth <= ray.near:
            return 0.0
        return gaussian_pixel_alpha(prims, i, ray.camera, ray.u, ray.v)

    def strategy(self, densify, schedule, *, pixels, **common):
        """3DGS's adaptive density control; its NDC-gradient threshold needs no scaling with the view size."""
        from radfield.core.train.strategy import GaussianStrategy

        gaussian = densify["gaussian"]
        return GaussianStrategy(schedule, grad_threshold=gaussian["grad_threshold"], prune_scale=gaussian["prune_scale"],
                                min_opacity=gaussian["min_opacity"], opacity_reset_every=gaussian["opacity_reset_every"],
                                **common)

    def from_points(self, geometry, settings, seed):
        return Gaussians(**geometry, opacities=torch.full((len(geometry["means"]),), INITIAL_OPACITY))

    def peak_density(self, prims, samples=128, seed=0):
        return torch.sigmoid(prims.opacities.detach())

    def to_gaussians(self, prims, components=1):
        return prims

    def bench_models(self, scene, generator):
        # σ = s/3: the 3σ splat covers the pixels of a neural primitive of radius s (bench/render.py)
        n = len(scene["means"])
        return {"gaussian": Gaussians(**{**scene, "log_scales": scene["log_scales"] - math.log(3.0)},
                                      opacities=torch.full((n,), 1.0))}


GAUSSIAN = register(GaussianKind())
backends.implement("view.gaussian", backends.FUSED_CPU, _fused_cpu_view)
backends.implement("view.gaussian", backends.TRITON, gpu.gaussian_view)
