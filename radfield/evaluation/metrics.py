"""Image quality metrics for evaluation: the same PSNR and SSIM the trainer uses.

    psnr(img, ref) -> dB over every pixel and channel, data range 1
    ssim(img, ref) -> mean SSIM, 11×11 Gaussian window (σ = 1.5), "valid" windows only: equal to
                      skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
                      use_sample_covariance=False, data_range=1, channel_axis=-1)

Images are (..., H, W, C) float tensors; clamp renders to [0, 1] before measuring them.

    per_condition(per_view, condition) -> the per-view figures averaged per value of a view
                           condition (a dynamic scene's moments, a capture's lights)

Both take mask= (..., H, W) bool, the valid pixels of an undistorted photo (radfield.core.train.losses
explains the rule): PSNR averages the squared error over the valid pixels' channels; SSIM
replaces the render's invalid pixels by the photo's and averages the SSIM map over the 11×11
windows that lie wholly on valid pixels (an all-valid mask gives the unmasked value).
"""

from collections.abc import Callable, Sequence
from typing import Any

from radfield.core.train.losses import psnr, ssim

__all__ = ["per_condition", "psnr", "ssim"]

PER_GROUP_FIGURES = ("psnr", "ssim", "lpips")


def per_condition(per_view: Sequence[dict[str, Any]], condition) -> list[dict[str, Any]]:
    """The means over the views (each with its `condition` entry, scene.json's form) of each value of
    a view condition (radfield/conditions), a row each: the value's entries (Condition.row: a
    dynamic scene's {"time"}, a capture's {"position" | "direction", "intensity"}), then "views",
    "psnr", "ssim", "lpips"; ascending by value where the condition is ordered (moments), else in
    the order values first appear. Every view counts once, so the overall mean is the
    views-weighted mean of these (a figure a view lacks, e.g. lpips None, is None for its value)."""
    def value(view):
        return condition.from_json(view[condition.name])

    groups = grouped(per_view, lambda view: condition.key(value(view)))
    keys = sorted(groups) if condition.ordered() else list(groups)
    return [{**condition.row(value(groups[k][0])), **means(groups[k])} for k in keys]


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
