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
from radfield.core.geometry.cameras import Camera
from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.core.kinds.base import INITIAL_ALPHA, PrimitiveKind, Primitives, register
from radfield.core.splat.gaussian import EWA_BLUR, ewa_view, pair_alpha, splat_bounds
from radfield.core.splat.kernels import ALPHA_MAX
from radfield.core.splat.sh import num_sh_coeffs
from radfield.core.splat.view import ViewFrame

INITIAL_OPACITY = math.log(INITIAL_ALPHA / (1.0 - INITIAL_ALPHA))  # logit of a new Gaussian's opacity, as 3DGS


@dataclass
class Gaussians(Primitives):
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


# --- the slow reference's α (core/render/reference.py) ---------------------------------------------

def gaussian_pixel_alpha(prims: Gaussians, i: int, camera: Camera, u: float, v: float) -> float:
    """EWA splat weight of Gaussian i at image point (u, v), straight from the 3DGS formulas."""
    w2c = torch.linalg.inv(camera.c2w)
    p = w2c[:3, :3] @ prims.means[i].double() + w2c[:3, 3]
    x, y, z = p.tolist()
    lim_x = (camera.cx / camera.fx + 0.15 * camera.width / camera.fx, (camera.width - camera.cx) / camera.fx + 0.15 * camera.width / camera.fx)
    lim_y = (camera.cy / camera.fy + 0.15 * camera.height / camera.fy, (camera.height - camera.cy) / camera.fy + 0.15 * camera.height / camera.fy)
    tx = z * min(max(x / z, -lim_x[0]), lim_x[1])
    ty = z * min(max(y / z, -lim_y[0]), lim_y[1])
    jac = torch.tensor([[camera.fx / z, 0, -camera.fx * tx / z**2], [0, camera.fy / z, -camera.fy * ty / z**2]], dtype=torch.float64)
    rot = quat_to_rotmat(prims.quats[i][None].double())[0]
    cov3 = rot @ torch.diag(torch.exp(2 * prims.log_scales[i].double())) @ rot.T
    cov2 = jac @ w2c[:3, :3] @ cov3 @ w2c[:3, :3].T @ jac.T + EWA_BLUR * torch.eye(2, dtype=torch.float64)
    delta = torch.tensor([u - (camera.fx * x / z + camera.cx), v - (camera.fy * y / z + camera.cy)], dtype=torch.float64)
    # 3DGS evaluates a splat only inside the square of radius ceil(3 √λ_max) around its mean
    radius = math.ceil(3.0 * math.sqrt(float(torch.linalg.eigvalsh(cov2)[-1])))
    if abs(float(delta[0])) > radius or abs(float(delta[1])) > radius:
        return 0.0
    power = -0.5 * float(delta @ torch.linalg.inv(cov2) @ delta)
    return min(ALPHA_MAX, float(torch.sigmoid(prims.opacities[i].double())) * math.exp(power))


class GaussianKind(PrimitiveKind):
    name = "gaussian"
    primitives = Gaussians
    own_params = {"opacities": ()}
    exact_gaussians = True
    support_radius = 3.0        # the 3σ ellipsoid the splat's bounds cover too
    bench_variants = ("gaussian",)

    def twin_view(self, prims, frame: ViewFrame):
        view, cov = ewa_view(prims, frame.camera, frame.w2c, frame.means_cam, frame.near)
        bounds, visible = splat_bounds(view[0], *cov, frame.depth, frame.camera, frame.near)
        return bounds, visible, view

    def pair_kernel(self, prims):
        return pair_alpha

    def reference_alpha(self, prims, i, ray, depth):
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
backends.implement(backends.view_op("gaussian"), backends.FUSED_CPU, _fused_cpu_view)
backends.implement(backends.view_op("gaussian"), backends.TRITON, gpu.gaussian_view)
