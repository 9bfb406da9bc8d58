"""Image quality metrics for evaluation: the same PSNR and SSIM the trainer uses.

    psnr(img, ref) -> dB over every pixel and channel, data range 1
    ssim(img, ref) -> mean SSIM, 11×11 Gaussian window (σ = 1.5), "valid" windows only: equal to
                      skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
                      use_sample_covariance=False, data_range=1, channel_axis=-1)

Images are (..., H, W, C) float tensors; clamp renders to [0, 1] before measuring them.

    per_time(per_view) -> the per-view figures of a dynamic scene's views averaged per moment ξ_t

Both take mask= (..., H, W) bool, the valid pixels of an undistorted photo (radfield.core.train.losses
explains the rule): PSNR averages the squared error over the valid pixels' channels; SSIM
replaces the render's invalid pixels by the photo's and averages the SSIM map over the 11×11
windows that lie wholly on valid pixels (an all-valid mask gives the unmasked value).
"""

from collections.abc import Sequence
from typing import Any

from radfield.core.train.losses import psnr, ssim

__all__ = ["per_time", "psnr", "ssim"]

PER_TIME_FIGURES = ("psnr", "ssim", "lpips")


def per_time(per_view: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """[{"time", "views", "psnr", "ssim", "lpips"}, ...] ascending in time: the means over the views
    (each with a "time") of each moment. Every view counts once, so the overall mean is the
    views-weighted mean of these (a figure a view lacks, e.g. lpips None, is None for its moment)."""
    moments: dict[float, list[dict[str, Any]]] = {}
    for view in per_view:
        moments.setdefault(view["time"], []).append(view)
    rows = []
    for time in sorted(moments):
        views = moments[time]
        row: dict[str, Any] = {"time": time, "views": len(views)}
        for key in PER_TIME_FIGURES:
            values = [v.get(key) for v in views]
            row[key] = None if any(x is None for x in values) else sum(values) / len(values)
        rows.append(row)
    return rows
