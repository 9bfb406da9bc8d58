"""A minimum primitive footprint, a training rule of anti-aliasing (the renderer's remedies, ray
jitter and supersampling, are core/render/antialias.py's).

Footprint floor (`train.min_footprint` = k, in pixels; Mip-Splatting's 3D filter, Yu et al. 2024,
§4.1, bounds each primitive's size below by the finest sampling interval of the training views):
after every optimiser step every scale axis is raised to at least k pixels of the primitive's
finest training view,

    s_i ← max(s_i, k · min over the views of z / f)                                        (2)

(z/f of the finest view among those whose image holds the centre, radfield.core.train.frequency.footprint
of a point, recomputed with the frequency cap's interval), so no primitive is thinner than k pixels
in any training view and none can fit detail between the pixel centres. A primitive no training
view's image holds is left alone.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from radfield.core.geometry.cameras import Camera
from radfield.core.train.frequency import footprint, view_stack
from radfield.core.train.strategy import refresh_interval, stale


PROBE = 1e-4  # scene units: the radius of the point whose footprint gives a view's pixel size z/f


class FootprintFloor:
    """Eq. (2) during training: `apply(params, step)` after each optimiser step raises
    params["log_scales"] to at least log(k · z/f) of each primitive's finest training view."""

    def __init__(self, cameras: Sequence[Camera], *, pixels: float, near: float, every: int = 100):
        if pixels < 0:
            raise ValueError(f"minimum footprint must be >= 0 pixels, got {pixels}")
        self.views = view_stack(cameras) if pixels > 0 else None
        self.pixels = pixels
        self.near = near
        self.every = max(int(every), 1)
        self._floor = None  # (P,) the floor on log s per primitive (−inf: unseen)

    @classmethod
    def for_training(cls, cameras: Sequence[Camera], cfg: dict, *, near: float) -> "FootprintFloor":
        """The floor of a training run from its `train` config section (refreshed at the frequency cap's interval)."""
        every = refresh_interval(cfg)
        return cls(cameras, pixels=cfg["min_footprint"], near=near, every=every)

    def floor(self, means: torch.Tensor) -> torch.Tensor:
        """log(k · z/f) per primitive (P,) of its finest training view, −inf for primitives no
        training view has in its image. A function of the means alone, so that raising the
        scales never moves the floor (a resumed run applies the floor the uninterrupted run did)."""
        # footprint() of a PROBE-sized primitive: ρ = f · PROBE / z over the views whose image holds the centre
        rho = footprint(means, torch.full_like(means[:, 0], PROBE), self.views, self.near)
        return torch.where(rho > 0, torch.log(self.pixels * PROBE / rho.clamp_min(1e-30)), -math.inf)

    @torch.no_grad()
    def apply(self, params: dict[str, torch.Tensor], step: int) -> None:
        if self.views is None:
            return
        log_scales = params["log_scales"]
        if stale(self._floor, log_scales.shape[0], step, self.every):
            self._floor = self.floor(params["means"].detach())
        # in place and idempotent: scales at or above the floor keep their bits
        torch.maximum(log_scales, self._floor[:, None].to(log_scales), out=log_scales)
