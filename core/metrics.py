"""Image quality metrics for evaluation: the same PSNR and SSIM the trainer uses.

    psnr(img, ref) -> dB over every pixel and channel, data range 1
    ssim(img, ref) -> mean SSIM, 11×11 Gaussian window (σ = 1.5), "valid" windows only: equal to
                      skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
                      use_sample_covariance=False, data_range=1, channel_axis=-1)

Images are (..., H, W, C) float tensors; clamp renders to [0, 1] before measuring them.
"""

from radfield.core.losses import psnr, ssim

__all__ = ["psnr", "ssim"]
