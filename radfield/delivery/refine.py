"""The export's refinement: `refine_gaussians` fits the moment-matched Gaussians of a neural model
(core/kinds/moment_matching.py) to renders of that model (for a run, whose cameras say where to
look): 3DGS renderers widen every splat by 0.3 px², which moment matching cannot know about and
which dominates splats of a pixel or two.
"""

from __future__ import annotations

import math

import torch

from radfield.core.kinds.gaussian import Gaussians


def orbit_views(cameras, count: int, seed: int = 0) -> list:
    """`count` random views around the object the `cameras` look at, in the band they cover: the
    centre is the point nearest every optical axis (least squares), each view's direction has an
    azimuth uniform about the cameras' mean up vector and an elevation and a distance uniform
    between the cameras' lowest and highest, and it takes the intrinsics of a random camera. These
    views show the model from between and beside the training cameras, so that Gaussians
    distilled on them also match the model where no photo looked (the test views)."""
    from radfield.core.geometry.cameras import Camera, look_at

    if count <= 0 or not cameras:
        return []
    g = torch.Generator().manual_seed(seed)
    eyes = torch.stack([c.c2w[:3, 3] for c in cameras])
    axes = torch.stack([c.c2w[:3, 2] for c in cameras])
    # the point nearest all optical axes: Σ (I − a aᵀ) x = Σ (I − a aᵀ) o
    proj = torch.eye(3, dtype=torch.float64) - axes[:, :, None] * axes[:, None, :]
    centre = torch.linalg.lstsq(proj.sum(0), (proj @ eyes[:, :, None]).sum(0)).solution[:, 0]
    up = torch.nn.functional.normalize(-torch.stack([c.c2w[:3, 1] for c in cameras]).mean(0), dim=0)
    offsets = eyes - centre
    dist = offsets.norm(dim=-1)
    elevation = torch.asin((offsets @ up / dist).clamp(-1, 1))
    side = torch.nn.functional.normalize(torch.linalg.cross(up, offsets[0]), dim=0)
    if not torch.isfinite(side).all() or side.norm() < 0.5:   # the first camera on the up axis
        side = torch.nn.functional.normalize(torch.linalg.cross(up, torch.eye(3, dtype=torch.float64)[int(up.abs().argmin())]), dim=0)
    front = torch.linalg.cross(side, up)
    uniform = lambda lo, hi: lo + (hi - lo) * torch.rand((), generator=g, dtype=torch.float64)
    views = []
    for i in range(count):
        azimuth = uniform(0.0, 2 * math.pi)
        el = uniform(elevation.min(), elevation.max())
        r = uniform(dist.min(), dist.max())
        direction = torch.cos(el) * (torch.cos(azimuth) * front + torch.sin(azimuth) * side) + torch.sin(el) * up
        # look_at's up must not be parallel to the view direction
        view_up = up if abs(float(direction @ up)) < 0.99 else front
        base = cameras[int(torch.randint(len(cameras), (), generator=g))]
        views.append(Camera(base.fx, base.fy, base.cx, base.cy, base.width, base.height,
                            look_at(centre + r * direction, centre, view_up), f"orbit_{i:04d}"))
    return views


def refine_gaussians(gaussians: Gaussians, teacher, cameras, train_cfg: dict, *, steps: int, extent: float,
                     background=(1.0, 1.0, 1.0), seed: int = 0, on_step=None, orbit: int = 0,
                     densify: bool = False) -> Gaussians:
    """Photometric refinement (distillation) of moment-matched Gaussians against renders of the
    `teacher` model (the neural primitives) from `cameras` and `orbit` random views around the
    object (orbit_views): radfield's trainer (core.trainer, 3DGS's Adam recipe from the `train`
    config section) for `steps` steps with the full SH degree. Without `densify` there is no
    population control, so the result keeps one Gaussian per moment-matched one; with it, 3DGS's
    clone/split/prune (the `train.densify.gaussian` recipe, no opacity reset) runs from a tenth to
    two thirds of the steps. The teacher's renders, not the photos, are the targets: the export
    stays a copy of the model (with its edits)."""
    from radfield.core.render.antialias import render_model
    from radfield.core.trainer.loop import train

    cameras = list(cameras) + orbit_views(cameras, orbit, seed)
    with torch.no_grad():  # the teacher as it looks (its own n × n rays a pixel); the student one ray a pixel
        targets = torch.stack([render_model(teacher, c, background=background).color.clamp(0, 1) for c in cameras])
    never = steps + 1
    if densify:
        every = max(1, steps // 10)
        plan = {"start": every, "stop": (2 * steps) // 3, "every": every}
    else:
        plan = {"start": never, "stop": never}
    rules = {**train_cfg["densify"], **plan,
             "gaussian": {**train_cfg["densify"]["gaussian"], "opacity_reset_every": never}}
    cfg = {**train_cfg, "iterations": steps, "max_primitives": None, "sh_degree": gaussians.sh_degree,
           "sh_increase_every": 1, "lambda_aniso": 0.0, "densify": rules, "checkpoint_every": never,
           "ray_jitter": 0.0, "min_footprint": 0.0, "random_background": False}
    state = train(gaussians, cameras, targets, cfg, background=background, extent=extent, seed=seed,
                  device=gaussians.means.device, on_step=on_step)
    return state.primitives()
