"""Training losses and image metrics. Images are channel-last float tensors (..., H, W, C) with
values in [0, 1] (what the renderer returns); every function reduces to a scalar tensor.

    loss = (1 − λ) L1 + λ D-SSIM + λ_aniso · anisotropy      (3DGS loss + Splat the Net §3.3)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

SSIM_WINDOW = 11    # taps of the Gaussian window (standard SSIM, Wang et al. 2004)
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2   # (K1 · data range)², data range 1
SSIM_C2 = 0.03**2


def l1(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean absolute error."""
    return (img - ref).abs().mean()


def psnr(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB for data range 1, over every pixel and channel
    (callers clamp renders to [0, 1] first when they report it as a metric)."""
    return -10.0 * torch.log10(((img - ref) ** 2).mean())


def ssim(img: torch.Tensor, ref: torch.Tensor, padding: str = "valid") -> torch.Tensor:
    """Mean structural similarity with the standard 11×11 Gaussian window (σ = 1.5, C1 = 0.01²,
    C2 = 0.03², population covariances), per channel, averaged over pixels and channels.

    padding="valid" averages only the windows that lie inside the image: this equals scikit-image's
    `structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
    data_range=1, channel_axis=-1)` and is the evaluation metric. padding="same" zero-pads the
    image by 5 pixels and averages every pixel, as 3DGS's training loss does (borders keep a gradient).
    Shapes: img, ref (..., H, W, C); H, W ≥ 11 for "valid".
    """
    if padding not in ("valid", "same"):
        raise ValueError(f"padding must be 'valid' or 'same', not {padding!r}")
    channels = img.shape[-1]
    x = img.reshape(-1, *img.shape[-3:]).movedim(-1, 1)   # (B, C, H, W)
    y = ref.reshape(-1, *ref.shape[-3:]).movedim(-1, 1)
    window = _gaussian_window(img.dtype, img.device)
    pad = SSIM_WINDOW // 2 if padding == "same" else 0

    def blur(z):  # separable Gaussian filter, one channel at a time (groups = C)
        z = F.conv2d(z, window.view(1, 1, 1, -1).expand(channels, 1, 1, -1), padding=(0, pad), groups=channels)
        return F.conv2d(z, window.view(1, 1, -1, 1).expand(channels, 1, -1, 1), padding=(pad, 0), groups=channels)

    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x * mu_x
    var_y = blur(y * y) - mu_y * mu_y
    cov_xy = blur(x * y) - mu_x * mu_y
    ssim_map = ((2 * mu_x * mu_y + SSIM_C1) * (2 * cov_xy + SSIM_C2)) / (
        (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (var_x + var_y + SSIM_C2))
    return ssim_map.mean()


def dssim(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """D-SSIM = 1 − SSIM, with the 3DGS training convention (padding="same")."""
    return 1.0 - ssim(img, ref, padding="same")


def photometric(img: torch.Tensor, ref: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
    """The 3DGS image loss (1 − λ) L1 + λ D-SSIM."""
    return (1.0 - lambda_dssim) * l1(img, ref) + lambda_dssim * dssim(img, ref)


def anisotropy(log_scales: torch.Tensor) -> torch.Tensor:
    """Splat the Net's geometry regulariser (§3.3, §5.3): the standard deviation of each
    primitive's scales relative to its smallest, std(s / min(s)), averaged over primitives
    (Bessel-corrected std, as the authors' code). log_scales (P, 3)."""
    scales = torch.exp(log_scales)
    ratio = scales / scales.amin(-1, keepdim=True)
    return ratio.std(-1).mean()


def _gaussian_window(dtype, device) -> torch.Tensor:
    """Normalised 1D Gaussian taps (11,), the same as scipy's gaussian_filter(sigma=1.5, truncate=3.5)."""
    x = torch.arange(SSIM_WINDOW, dtype=torch.float64) - SSIM_WINDOW // 2
    taps = torch.exp(-x * x / (2 * SSIM_SIGMA**2))
    return (taps / taps.sum()).to(dtype=dtype, device=device)

