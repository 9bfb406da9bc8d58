"""Image quality metrics for evaluation: the same PSNR and SSIM the trainer uses.

    psnr(img, ref) -> dB over every pixel and channel, data range 1
    ssim(img, ref) -> mean SSIM, 11×11 Gaussian window (σ = 1.5), "valid" windows only: equal to
                      skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
                      use_sample_covariance=False, data_range=1, channel_axis=-1)

Images are (..., H, W, C) float tensors; clamp renders to [0, 1] before measuring them.

    per_time(per_view) -> the per-view figures of a dynamic scene's views averaged per moment ξ_t
    per_light(per_view) -> the per-view figures of a one-light-at-a-time capture's views averaged per light

Both take mask= (..., H, W) bool, the valid pixels of an undistorted photo (radfield.core.train.losses
explains the rule): PSNR averages the squared error over the valid pixels' channels; SSIM
replaces the render's invalid pixels by the photo's and averages the SSIM map over the 11×11
windows that lie wholly on valid pixels (an all-valid mask gives the unmasked value).
"""

import json
from collections.abc import Callable, Sequence
from typing import Any

from radfield.core.train.losses import psnr, ssim

__all__ = ["per_light", "per_time", "psnr", "ssim"]

PER_GROUP_FIGURES = ("psnr", "ssim", "lpips")


def per_time(per_view: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """[{"time", "views", "psnr", "ssim", "lpips"}, ...] ascending in time: the means over the views
    (each with a "time") of each moment. Every view counts once, so the overall mean is the
    views-weighted mean of these (a figure a view lacks, e.g. lpips None, is None for its moment)."""
    return [{"time": views[0]["time"], **means(views)}
            for _, views in sorted(grouped(per_view, lambda v: v["time"]).items())]


def per_light(per_view: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """[{"position" | "direction": [x, y, z], "intensity", "views", "psnr", "ssim", "lpips"}, ...]:
    the means over the views lit by each light (each view with a "light", scene.json's form), in
    the order the lights first appear; the overall mean is their views-weighted mean, as per_time's."""
    return [{**views[0]["light"], **means(views)}
            for views in grouped(per_view, lambda v: json.dumps(v["light"], sort_keys=True)).values()]


def grouped(per_view: Sequence[dict[str, Any]], key: Callable[[dict], Any]) -> dict[Any, list[dict[str, Any]]]:
    """The views by key(view), in the order the keys first appear."""
    groups: dict[Any, list[dict[str, Any]]] = {}
    for view in per_view:
        groups.setdefault(key(view), []).append(view)
    return groups


def means(views: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """{"views": N, figure: the views' mean or None when a view lacks it, ...} (PER_GROUP_FIGURES)."""
    row: dict[str, Any] = {"views": len(views)}
    for key in PER_GROUP_FIGURES:
        values = [v.get(key) for v in views]
        row[key] = None if any(x is None for x in values) else sum(values) / len(values)
    return row
