"""Op "photometric" on the Triton backend: a training step's image loss, (1 − λ) L1 + λ D-SSIM, in
two launches forward and two backward (loss_kernels.py: the window's rows, then its columns)
where its torch twin (core/train/losses.py: _photometric) launches some forty ops each way; the
fused CPU op's signature."""

from __future__ import annotations

import torch

from radfield.core.backends.gpu.launch import PREPARE_OPTIONS, launching
from radfield.util.transfer import device_constants


class _Photometric(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, y, taps, lambda_dssim, c1, c2):
        from radfield.core.backends.gpu import loss_kernels as K

        x, y, taps = x.contiguous(), y.detach().contiguous(), taps.detach().contiguous()
        _, height, width, channels = x.shape
        total = x.numel()
        # (C1, C2, (1 − λ)/n, λ/n) in the images' dtype, made once per size, not every step
        consts = device_constants((c1, c2, (1.0 - lambda_dssim) / total, lambda_dssim / total), x.dtype, x.device)
        grid = (-(-total // K.BLOCK),)
        rows = x.new_empty(5 * total)           # the rows pass's sums of x, y, x², y², xy
        abk = x.new_empty(3 * total)            # the map's derivatives A, B, K (loss_kernels.py)
        sums = x.new_empty(grid[0], 2)          # each program's Σ S and Σ |x − y|
        sizes = (total, height, width, channels)
        ctx.grid = grid, sizes
        with launching():
            K.ssim_rows[grid](x, y, taps, rows, *sizes, BLOCK=K.BLOCK, **PREPARE_OPTIONS)
            K.ssim_columns[grid](x, y, taps, consts, rows, abk, sums, *sizes, BLOCK=K.BLOCK, **PREPARE_OPTIONS)
        ctx.save_for_backward(x, y, taps, consts, abk)
        ssim_sum, l1_sum = sums.sum(0).unbind()
        return (1.0 - lambda_dssim) / total * l1_sum + lambda_dssim * (1.0 - ssim_sum / total)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        from radfield.core.backends.gpu import loss_kernels as K

        x, y, taps, consts, abk = ctx.saved_tensors
        grid, sizes = ctx.grid
        rows = x.new_empty(3 * x.numel())       # the rows pass's sums of A, B, K
        out = torch.empty_like(x)
        with launching():
            K.adjoint_rows[grid](taps, abk, rows, *sizes, BLOCK=K.BLOCK, **PREPARE_OPTIONS)
            K.adjoint_columns[grid](x, y, taps, consts, rows, grad.contiguous(), out, *sizes, BLOCK=K.BLOCK,
                                    **PREPARE_OPTIONS)
        return out, None, None, None, None, None


def photometric(x, y, taps, lambda_dssim: float, c1: float, c2: float) -> torch.Tensor:
    """(1 − λ) mean|x − y| + λ (1 − mean SSIM map) of images x, y (B, H, W, C), the "same" map (zero
    padding 5), window taps (11,); differentiable w.r.t. x only (as fused.photometric)."""
    return _Photometric.apply(x, y, taps, float(lambda_dssim), float(c1), float(c2))
