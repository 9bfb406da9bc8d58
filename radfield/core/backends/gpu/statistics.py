"""Ops "neural_accumulate" and "gaussian_accumulate" on the Triton backend: population control's
statistics of a view (statistics_kernels.py), with the fused CPU ops' signatures."""

from __future__ import annotations

import torch

from radfield.core.backends.gpu.launch import PREPARE_OPTIONS, launching, padded
from radfield.util.transfer import device_constants


def neural_accumulate(grad_acc, count_acc, means, log_scales, g_w1, g_b1, g_w2, g_b2, w2c, normals,
                      radius_scale: float, near: float) -> None:
    """Op "neural_accumulate" on Triton: one view's visibility and MLP-gradient signal added into
    the accumulators in place (twin: core/train/strategy.py `_Strategy.accumulate`)."""
    _accumulate(grad_acc, count_acc, means, log_scales, None, (g_w1, g_b1, g_w2, g_b2), w2c, normals,
                (radius_scale, near, 1.0, 1.0, 0.0, 0.0))


def gaussian_accumulate(grad_acc, count_acc, means, log_scales, grad_means, w2c, normals, radius_scale: float,
                        near: float, fx: float, fy: float, width: float, height: float) -> None:
    """Op "gaussian_accumulate" on Triton: one view's visibility and screen-space gradient signal
    added into the accumulators in place."""
    _accumulate(grad_acc, count_acc, means, log_scales, grad_means, None, w2c, normals,
                (radius_scale, near, fx, fy, width / 2, height / 2))


@torch.no_grad()
def _accumulate(grad_acc, count_acc, means, log_scales, grad_means, mlp_grads, w2c, normals, numbers) -> None:
    from radfield.core.backends.gpu import statistics_kernels as K

    count = means.shape[0]
    if count == 0:
        return
    frame = torch.cat([w2c.reshape(12), normals.reshape(12), device_constants(numbers, means.dtype, means.device)])
    neural = mlp_grads is not None
    g_w1, g_b1, g_w2, g_b2 = (t.contiguous() for t in mlp_grads) if neural else (means,) * 4
    units = g_b1.shape[1] if neural else 1
    with launching():
        K.accumulate[(-(-count // K.BLOCK),)](grad_acc, count_acc, means.detach().contiguous(),
                                              log_scales.detach().contiguous(),
                                              means if neural else grad_means.contiguous(), g_w1, g_b1, g_w2, g_b2,
                                              frame, count, units, NP=padded(units), NEURAL=neural, BLOCK=K.BLOCK,
                                              **PREPARE_OPTIONS)
