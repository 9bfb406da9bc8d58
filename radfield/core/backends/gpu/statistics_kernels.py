"""The Triton kernel of a view's population-control statistics (core/backends/gpu/statistics.py
wraps it as ops "neural_accumulate" and "gaussian_accumulate"; the twin is
core/train/strategy.py `_Strategy.accumulate`, the fused CPU op csrc/strategy_kernels.cpp): one
lane per primitive, added into the accumulators in place, in place of some twenty torch ops a view.

    visible_p = min_j n_j·p_p ≥ −r_p  and  z_p + r_p > near,   p_p = R μ_p + t (camera space),
                r_p = radius_scale · exp(max ℓ_p), n_j the unit inward normals of the 4 side planes
    grad_p  += visible_p ? signal_p : 0,   count_p += visible_p

    neural signal (Splat the Net): ‖∂L/∂W1‖ + ‖∂L/∂b1‖ + ‖∂L/∂W2‖ + |∂L/∂b2| of the primitive's MLP
    Gaussian signal (3DGS's screen-space gradient, in NDC units): with g = R ∂L/∂μ_p and z_p the
        depth, hypot(g_x z_p / fx · W/2, g_y z_p / fy · H/2)

frame = (w2c rows (3 × 4, row-major), the normals (4 × 3), radius_scale, near, fx, fy, W/2, H/2)
in the accumulators' dtype. Imported when a strategy on the "triton" backend gathers statistics.
"""

from __future__ import annotations

import triton
import triton.language as tl

BLOCK = 128   # primitives per program


@triton.jit
def _plane(j: tl.constexpr, frame_ptr, x, y, z):
    """n_j · p for side plane j."""
    return (tl.load(frame_ptr + 12 + 3 * j) * x + tl.load(frame_ptr + 13 + 3 * j) * y
            + tl.load(frame_ptr + 14 + 3 * j) * z)


@triton.jit
def accumulate(grad_acc_ptr, count_acc_ptr, means_ptr, log_scales_ptr, g_means_ptr, g_w1_ptr, g_b1_ptr, g_w2_ptr,
               g_b2_ptr, frame_ptr, P, N, NP: tl.constexpr, NEURAL: tl.constexpr, BLOCK: tl.constexpr):
    """Add one view's signal and visibility into grad_acc and count_acc (P,). NEURAL: the MLP's
    gradients g_w1 (P, N, 3), g_b1 (P, N), g_w2 (P, N), g_b2 (P,) (g_means unused); else the means'
    gradient g_means (P, 3) (the MLP's unused)."""
    p = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = p < P
    mx = tl.load(means_ptr + 3 * p, mask=live, other=0.0)
    my = tl.load(means_ptr + 3 * p + 1, mask=live, other=0.0)
    mz = tl.load(means_ptr + 3 * p + 2, mask=live, other=0.0)
    x = tl.load(frame_ptr) * mx + tl.load(frame_ptr + 1) * my + tl.load(frame_ptr + 2) * mz + tl.load(frame_ptr + 3)
    y = tl.load(frame_ptr + 4) * mx + tl.load(frame_ptr + 5) * my + tl.load(frame_ptr + 6) * mz + tl.load(frame_ptr + 7)
    z = tl.load(frame_ptr + 8) * mx + tl.load(frame_ptr + 9) * my + tl.load(frame_ptr + 10) * mz + tl.load(frame_ptr + 11)
    l0 = tl.load(log_scales_ptr + 3 * p, mask=live, other=0.0)
    l1 = tl.load(log_scales_ptr + 3 * p + 1, mask=live, other=0.0)
    l2 = tl.load(log_scales_ptr + 3 * p + 2, mask=live, other=0.0)
    radius = tl.load(frame_ptr + 24) * tl.exp(tl.maximum(tl.maximum(l0, l1), l2))
    nearest = tl.minimum(tl.minimum(_plane(0, frame_ptr, x, y, z), _plane(1, frame_ptr, x, y, z)),
                         tl.minimum(_plane(2, frame_ptr, x, y, z), _plane(3, frame_ptr, x, y, z)))
    visible = live & (nearest >= -radius) & (z + radius > tl.load(frame_ptr + 25))
    if NEURAL:
        k = tl.arange(0, NP)
        unit = live[:, None] & (k[None, :] < N)
        row = p[:, None] * N + k[None, :]
        w0 = tl.load(g_w1_ptr + 3 * row, mask=unit, other=0.0)
        w1 = tl.load(g_w1_ptr + 3 * row + 1, mask=unit, other=0.0)
        w2 = tl.load(g_w1_ptr + 3 * row + 2, mask=unit, other=0.0)
        b1 = tl.load(g_b1_ptr + row, mask=unit, other=0.0)
        v2 = tl.load(g_w2_ptr + row, mask=unit, other=0.0)
        signal = (tl.sqrt(tl.sum(w0 * w0 + w1 * w1 + w2 * w2, axis=1)) + tl.sqrt(tl.sum(b1 * b1, axis=1))
                  + tl.sqrt(tl.sum(v2 * v2, axis=1)) + tl.abs(tl.load(g_b2_ptr + p, mask=live, other=0.0)))
    else:
        gx = tl.load(g_means_ptr + 3 * p, mask=live, other=0.0)
        gy = tl.load(g_means_ptr + 3 * p + 1, mask=live, other=0.0)
        gz = tl.load(g_means_ptr + 3 * p + 2, mask=live, other=0.0)
        cx = tl.load(frame_ptr) * gx + tl.load(frame_ptr + 1) * gy + tl.load(frame_ptr + 2) * gz
        cy = tl.load(frame_ptr + 4) * gx + tl.load(frame_ptr + 5) * gy + tl.load(frame_ptr + 6) * gz
        ndc_x = cx * z / tl.load(frame_ptr + 26) * tl.load(frame_ptr + 28)
        ndc_y = cy * z / tl.load(frame_ptr + 27) * tl.load(frame_ptr + 29)
        signal = tl.sqrt(ndc_x * ndc_x + ndc_y * ndc_y)
    tl.store(grad_acc_ptr + p, tl.load(grad_acc_ptr + p, mask=live, other=0.0) + tl.where(visible, signal, 0.0),
             mask=live)
    tl.store(count_acc_ptr + p, tl.load(count_acc_ptr + p, mask=live, other=0.0) + visible.to(mx.dtype), mask=live)
