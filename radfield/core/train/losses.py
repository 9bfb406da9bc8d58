"""Training losses and image metrics. Images are channel-last float tensors (..., H, W, C) with
values in [0, 1] (what the renderer returns); every function reduces to a scalar tensor.

    loss = (1 − λ) L1 + λ D-SSIM + λ_aniso · anisotropy      (3DGS loss + Splat the Net §3.3)
           + λ_w1 · frequency_magnitude + λ_density · density_magnitude   (neural primitives; off by default)

Valid-pixel masks: `mask` (..., H, W) bool marks the pixels that hold image content (undistortion
leaves invalid, black pixels at the borders: radfield.datasets.views.Dataset.load_valid_mask).
Every function then measures the valid pixels only. L1 and PSNR average over the valid pixels'
channels; SSIM first replaces the invalid pixels of `img` by those of `ref` (so they add no
difference inside a window) and then averages its map over the windows described in `ssim`.
No gradient reaches an invalid pixel. mask=None is every pixel valid.

The SSIM map, the photometric loss and the anisotropy run on the best kernel backend for the
tensors' device and dtype (radfield.core.backends: the fused CPU ops of core/backends/csrc/loss_kernels.cpp);
`_ssim_map`, `_photometric` and `_anisotropy` are their readable torch twins.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from radfield.core import backends
from radfield.util.transfer import device_constants

SSIM_WINDOW = 11    # taps of the Gaussian window (standard SSIM, Wang et al. 2004)
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2   # (K1 · data range)², data range 1
SSIM_C2 = 0.03**2


def l1(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean absolute error (over the valid pixels' channels)."""
    return _masked_mean((img - ref).abs(), mask)


def psnr(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB for data range 1, over every (valid) pixel and channel:
    −10 log10(Σ_valid (img − ref)² / (3 · #valid)). Callers clamp renders to [0, 1] first when
    they report it as a metric."""
    return -10.0 * torch.log10(_masked_mean((img - ref) ** 2, mask))


def ssim(img: torch.Tensor, ref: torch.Tensor, padding: str = "valid", mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean structural similarity with the standard 11×11 Gaussian window (σ = 1.5, C1 = 0.01²,
    C2 = 0.03², population covariances), per channel, averaged over pixels and channels.

    padding="valid" averages only the windows that lie inside the image: this equals scikit-image's
    `structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
    data_range=1, channel_axis=-1)` and is the evaluation metric. padding="same" zero-pads the
    image by 5 pixels and averages every pixel, as 3DGS's training loss does (borders keep a gradient).
    Shapes: img, ref (..., H, W, C); H, W ≥ 11 for "valid".

    With a valid-pixel mask (..., H, W): img's invalid pixels are replaced by ref's, then
    "valid" averages the SSIM map over the windows whose whole 11×11 support is valid pixels
    (on a mask that is all valid: every window inside the image, as without a mask), and "same"
    over the windows centred on a valid pixel. ValueError when no window qualifies.
    """
    if padding not in ("valid", "same"):
        raise ValueError(f"padding must be 'valid' or 'same', not {padding!r}")
    if mask is not None:
        img = torch.where(mask[..., None], img, ref)
    pad = SSIM_WINDOW // 2 if padding == "same" else 0
    x = img.reshape(-1, *img.shape[-3:])   # (B, H, W, C)
    y = ref.reshape(-1, *ref.shape[-3:])
    window = _gaussian_window(img.dtype, img.device)
    fast = backends.kernel(backends.Op.SSIM_MAP, img.device, img.dtype)
    if fast is not None and ref.dtype == img.dtype and not ref.requires_grad:
        ssim_map = fast(x, y, window, pad, SSIM_C1, SSIM_C2)   # fused: core/backends/csrc/loss_kernels.cpp
    else:
        ssim_map = _ssim_map(x, y, window, pad)
    if mask is None:
        return ssim_map.mean()
    m = mask.reshape(-1, 1, *mask.shape[-2:]).to(img.dtype)   # (B, 1, H, W)
    if padding == "valid":  # windows lying on valid pixels only: a box count of 11 × 11
        box = torch.ones(1, 1, SSIM_WINDOW, SSIM_WINDOW, dtype=img.dtype, device=img.device)
        m = (F.conv2d(m, box) > SSIM_WINDOW**2 - 0.5).to(img.dtype)
    weight = m.movedim(1, -1).expand_as(ssim_map)
    if not bool(weight.sum() > 0):
        raise ValueError("SSIM: no 11×11 window lies on valid pixels")
    return (ssim_map * weight).sum() / weight.sum()


def _ssim_map(x: torch.Tensor, y: torch.Tensor, window: torch.Tensor, pad: int) -> torch.Tensor:
    """The readable torch twin of the fused SSIM map: images (B, H, W, C) -> map (B, Ho, Wo, C)."""
    channels = x.shape[-1]
    x, y = x.movedim(-1, 1), y.movedim(-1, 1)   # (B, C, H, W)

    def blur(z):  # separable Gaussian filter, one channel at a time (groups = C)
        z = F.conv2d(z, window.view(1, 1, 1, -1).expand(channels, 1, 1, -1), padding=(0, pad), groups=channels)
        return F.conv2d(z, window.view(1, 1, -1, 1).expand(channels, 1, -1, 1), padding=(pad, 0), groups=channels)

    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x * mu_x
    var_y = blur(y * y) - mu_y * mu_y
    cov_xy = blur(x * y) - mu_x * mu_y
    ssim_map = ((2 * mu_x * mu_y + SSIM_C1) * (2 * cov_xy + SSIM_C2)) / (
        (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (var_x + var_y + SSIM_C2))
    return ssim_map.movedim(1, -1)


def dssim(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """D-SSIM = 1 − SSIM, with the 3DGS training convention (padding="same")."""
    return 1.0 - ssim(img, ref, padding="same", mask=mask)


def photometric(img: torch.Tensor, ref: torch.Tensor, lambda_dssim: float,
                mask: torch.Tensor | None = None) -> torch.Tensor:
    """The 3DGS image loss (1 − λ) L1 + λ D-SSIM (over the valid pixels of `mask`).

    Without a mask, on a kernel backend (the fused CPU path: one C++ op, core/backends/csrc/loss_kernels.cpp)
    it and its image gradient are computed in one pass each: the composition below is its readable
    twin, whose gradient it reproduces bit for bit (its value: to the last bits of the float means)."""
    fast = backends.kernel(backends.Op.PHOTOMETRIC, img.device, img.dtype) if mask is None and img.dim() >= 3 else None
    if fast is not None and ref.dtype == img.dtype and ref.shape == img.shape and not ref.requires_grad:
        x, y = img.reshape(-1, *img.shape[-3:]), ref.reshape(-1, *ref.shape[-3:])
        return fast(x, y, _gaussian_window(img.dtype, img.device), lambda_dssim, SSIM_C1, SSIM_C2)
    return _photometric(img, ref, lambda_dssim, mask)


def _photometric(img: torch.Tensor, ref: torch.Tensor, lambda_dssim: float,
                 mask: torch.Tensor | None = None) -> torch.Tensor:
    """The readable twin of the fused photometric op: L1 and D-SSIM as separate terms."""
    return (1.0 - lambda_dssim) * l1(img, ref, mask) + lambda_dssim * dssim(img, ref, mask)


def anisotropy(log_scales: torch.Tensor) -> torch.Tensor:
    """Splat the Net's geometry regulariser (§3.3, §5.3): the standard deviation of each
    primitive's scales relative to its smallest, std(s / min(s)), averaged over primitives
    (Bessel-corrected std, as the authors' code). log_scales (P, 3)."""
    fast = backends.kernel(backends.Op.ANISOTROPY, log_scales.device, log_scales.dtype)
    if fast is not None:
        return fast(log_scales)   # fused: core/backends/csrc/loss_kernels.cpp
    return _anisotropy(log_scales)


def _anisotropy(log_scales: torch.Tensor) -> torch.Tensor:
    """The readable torch twin of the fused anisotropy op."""
    scales = torch.exp(log_scales)
    ratio = scales / scales.amin(-1, keepdim=True)
    return ratio.std(-1).mean()


def frequency_magnitude(w1: torch.Tensor) -> torch.Tensor:
    """Penalty on the density MLP's frequencies: mean over primitives of ‖W1‖²_F (w1 (P, N, 3)).
    The cosines of eq. 5 oscillate at ω0 · W1 per unit of u: a small ‖W1‖ keeps each
    primitive's density smooth, so it cannot carve view-specific detail."""
    return w1.square().sum((-2, -1)).mean()


def density_magnitude(w2: torch.Tensor, b2: torch.Tensor) -> torch.Tensor:
    """Penalty on the density level: mean over primitives of ‖W2‖₁ + |b2|, the bound on σ of
    eq. 6 (an L1 opacity regulariser for neural primitives). w2 (P, N), b2 (P,)."""
    return (w2.abs().sum(-1) + b2.abs()).mean()


def _masked_mean(values: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Mean of (..., H, W, C) values over the channels of the pixels where mask (..., H, W) is true."""
    if mask is None:
        return values.mean()
    weight = mask[..., None].to(values.dtype).expand_as(values)
    return (values * weight).sum() / weight.sum()


def _gaussian_taps() -> tuple[float, ...]:
    """Normalised 1D Gaussian taps (11,), the same as scipy's gaussian_filter(sigma=1.5, truncate=3.5)."""
    x = torch.arange(SSIM_WINDOW, dtype=torch.float64) - SSIM_WINDOW // 2
    taps = torch.exp(-x * x / (2 * SSIM_SIGMA**2))
    return tuple((taps / taps.sum()).tolist())


# made at import, so that no training step reads them off a tensor (a host read in the step's
# count, tests/test_triton.py: test_a_training_step_reads_the_device_once_a_view)
GAUSSIAN_TAPS = _gaussian_taps()


def _gaussian_window(dtype, device) -> torch.Tensor:
    """The taps as a tensor, made once per (dtype, device), not each training step (callers never
    write to it)."""
    return device_constants(GAUSSIAN_TAPS, dtype, device)

