"""Image quality metrics for evaluation: the same PSNR and SSIM the trainer uses.

    psnr(img, ref) -> dB over every pixel and channel, data range 1
    ssim(img, ref) -> mean SSIM, 11×11 Gaussian window (σ = 1.5), "valid" windows only: equal to
                      skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
                      use_sample_covariance=False, data_range=1, channel_axis=-1)

Images are (..., H, W, C) float tensors; clamp renders to [0, 1] before measuring them.

Both take mask= (..., H, W) bool, the valid pixels of an undistorted photo (radfield.core.train.losses
explains the rule): PSNR averages the squared error over the valid pixels' channels; SSIM
replaces the render's invalid pixels by the photo's and averages the SSIM map over the 11×11
windows that lie wholly on valid pixels (an all-valid mask gives the unmasked value).
"""

from radfield.core.train.losses import psnr, ssim

__all__ = ["psnr", "ssim"]
