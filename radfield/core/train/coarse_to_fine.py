"""Coarse to fine (issue 40): the early steps train on downscaled views, the resolution doubling on a
schedule until full size, as DashGaussian schedules 3DGS's rendering resolution (Chen et al. 2025).

A step's cost is its pixel–primitive pairs: at 1/f of each side a view has 1/f² of the pixels and
each primitive's footprint 1/f² of the pixels, so the early steps, when the model is coarse anyway,
cost a fraction of a full-size step. With `train.coarse_levels` = L > 0 the views start at 1/2^L
of their size and double L times at equal intervals, reaching full size at `train.coarse_until` ×
iterations (`factor_at`); L = 0 trains at full size throughout.

The downscaled targets are area averages of the photos (what a camera of larger pixels records),
the cameras `Camera.scaled` (the same rays through the pixels' centres); a pixel of a downscaled
mask is valid when every photo pixel under it is. The densification statistics stay those of
full-size views: the loss is a mean over a view's pixels, so a primitive's gradient signal grows
as 1/√pixels (core/train/strategy.py), f times at 1/f of the side; each view's gradients are
divided by f before they are accumulated.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from radfield.core.geometry.cameras import Camera


def factor_at(step: int, iterations: int, levels: int, until: float) -> int:
    """The downscale factor of the training views at `step` (counted from 0): 2^L for the first
    1/L of the coarse steps, then 2^(L−1), … and 1 from step until·iterations on."""
    end = until * iterations
    if levels <= 0 or step >= end:
        return 1
    return 2 ** (levels - math.floor(step * levels / end))


class ViewPyramid:
    """The training views at each downscale factor asked for, made once and kept (a few MB each)."""

    def __init__(self, cameras: Sequence[Camera], images: torch.Tensor, masks: torch.Tensor | None,
                 alphas: torch.Tensor | None):
        self._levels = {1: (list(cameras), images, masks, alphas)}

    def at(self, factor: int) -> tuple[list[Camera], torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """(cameras, images (N, h, w, 3), masks (N, h, w) or None, alphas (N, h, w) or None) at 1/factor."""
        if factor not in self._levels:
            cameras, images, masks, alphas = self._levels[1]
            small = [camera.scaled(1.0 / factor) for camera in cameras]
            size = (small[0].height, small[0].width)
            self._levels[factor] = (small, area(images.permute(0, 3, 1, 2), size).permute(0, 2, 3, 1).contiguous(),
                                    None if masks is None else area(masks[:, None].float(), size)[:, 0] >= 1.0 - 1e-6,
                                    None if alphas is None else area(alphas[:, None], size)[:, 0])
        return self._levels[factor]


def area(stack: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(N, C, H, W) averaged over the photo pixels under each pixel of `size` (h, w)."""
    return torch.nn.functional.interpolate(stack, size=size, mode="area")
