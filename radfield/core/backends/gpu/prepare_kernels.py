"""The Triton kernels of the per-view, per-primitive preparation (core/backends/gpu/preparation.py
wraps them in autograd ops): one lane per primitive, forward and hand-written backward, in place of
the dozens of small torch ops each of their twins launches.

    sh_color_forward / sh_color_backward    colour = max(Σ_k Y_k(d̂) sh_k + 0.5, 0), d̂ = v/|v|,
                                            v = μ − o (twin: core/splat/sh.py sh_to_color; the
                                            fused CPU op: csrc/prepare_kernels.cpp sh_color)

The basis is 3DGS's real SH up to degree 3, in its order and signs (core/splat/sh.py). Imported
only when the "triton" backend prepares a view (as the view kernels; TRITON_INTERPRET=1 runs them
on CPU tensors in the tests).
"""

from __future__ import annotations

import triton
import triton.language as tl

BLOCK = 128   # primitives per program



@triton.jit
def _basis(k: tl.constexpr, x, y, z):
    """Y_k at the unit direction (x, y, z) and its gradient (∂x, ∂y, ∂z), as csrc/prepare_kernels.cpp sh_basis
    (the constants of core/splat/sh.py: constexpr locals, so that a float64 kernel reads them in
    float64; a plain local is made a float32 scalar, a kernel cannot read a module global)."""
    C0: tl.constexpr = 0.28209479177387814
    C1: tl.constexpr = 0.4886025119029199
    C2_0: tl.constexpr = 1.0925484305920792
    C2_1: tl.constexpr = -1.0925484305920792
    C2_2: tl.constexpr = 0.31539156525252005
    C2_3: tl.constexpr = -1.0925484305920792
    C2_4: tl.constexpr = 0.5462742152960396
    C3_0: tl.constexpr = -0.5900435899266435
    C3_1: tl.constexpr = 2.890611442640554
    C3_2: tl.constexpr = -0.4570457994644658
    C3_3: tl.constexpr = 0.3731763325901154
    C3_4: tl.constexpr = -0.4570457994644658
    C3_5: tl.constexpr = 1.445305721320277
    C3_6: tl.constexpr = -0.5900435899266435
    zero = x * 0.0
    if k == 0:
        return zero + C0, zero, zero, zero
    elif k == 1:
        return -C1 * y, zero, zero - C1, zero
    elif k == 2:
        return C1 * z, zero, zero, zero + C1
    elif k == 3:
        return -C1 * x, zero - C1, zero, zero
    elif k == 4:
        return C2_0 * x * y, C2_0 * y, C2_0 * x, zero
    elif k == 5:
        return C2_1 * y * z, zero, C2_1 * z, C2_1 * y
    elif k == 6:
        return C2_2 * (2.0 * z * z - x * x - y * y), C2_2 * -2.0 * x, C2_2 * -2.0 * y, C2_2 * 4.0 * z
    elif k == 7:
        return C2_3 * x * z, C2_3 * z, zero, C2_3 * x
    elif k == 8:
        return C2_4 * (x * x - y * y), C2_4 * 2.0 * x, C2_4 * -2.0 * y, zero
    elif k == 9:
        return C3_0 * y * (3.0 * x * x - y * y), C3_0 * 6.0 * x * y, C3_0 * (3.0 * x * x - 3.0 * y * y), zero
    elif k == 10:
        return C3_1 * x * y * z, C3_1 * y * z, C3_1 * x * z, C3_1 * x * y
    elif k == 11:
        return (C3_2 * y * (4.0 * z * z - x * x - y * y), C3_2 * -2.0 * x * y,
                C3_2 * (4.0 * z * z - x * x - 3.0 * y * y), C3_2 * 8.0 * y * z)
    elif k == 12:
        return (C3_3 * z * (2.0 * z * z - 3.0 * x * x - 3.0 * y * y), C3_3 * -6.0 * x * z, C3_3 * -6.0 * y * z,
                C3_3 * (6.0 * z * z - 3.0 * x * x - 3.0 * y * y))
    elif k == 13:
        return (C3_4 * x * (4.0 * z * z - x * x - y * y), C3_4 * (4.0 * z * z - 3.0 * x * x - y * y),
                C3_4 * -2.0 * x * y, C3_4 * 8.0 * x * z)
    elif k == 14:
        return C3_5 * z * (x * x - y * y), C3_5 * 2.0 * x * z, C3_5 * -2.0 * y * z, C3_5 * (x * x - y * y)
    else:
        return C3_6 * x * (x * x - 3.0 * y * y), C3_6 * (3.0 * x * x - 3.0 * y * y), C3_6 * -6.0 * x * y, zero


@triton.jit
def _direction(v_ptr, p, live):
    """v = μ − o of primitives p, its norm (as torch's normalize: at least 1e-12) and d̂ = v/|v|."""
    vx = tl.load(v_ptr + 3 * p, mask=live, other=1.0)
    vy = tl.load(v_ptr + 3 * p + 1, mask=live, other=0.0)
    vz = tl.load(v_ptr + 3 * p + 2, mask=live, other=0.0)
    norm = tl.maximum(tl.sqrt(vx * vx + vy * vy + vz * vz), 1e-12)
    return vx, vy, vz, norm, vx / norm, vy / norm, vz / norm


@triton.jit
def sh_color_forward(sh_ptr, v_ptr, out_ptr, P, K, COEFFS: tl.constexpr, BLOCK: tl.constexpr):
    """colour (P, 3) of sh (P, K, 3) at v (P, 3): the first COEFFS = (degree + 1)² coefficients."""
    p = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = p < P
    _, _, _, _, x, y, z = _direction(v_ptr, p, live)
    r = x * 0.0
    g = x * 0.0
    b = x * 0.0
    for k in tl.static_range(COEFFS):
        basis, _, _, _ = _basis(k, x, y, z)
        base = sh_ptr + (p * K + k) * 3
        r += basis * tl.load(base, mask=live, other=0.0)
        g += basis * tl.load(base + 1, mask=live, other=0.0)
        b += basis * tl.load(base + 2, mask=live, other=0.0)
    tl.store(out_ptr + 3 * p, tl.maximum(r + 0.5, 0.0), mask=live)
    tl.store(out_ptr + 3 * p + 1, tl.maximum(g + 0.5, 0.0), mask=live)
    tl.store(out_ptr + 3 * p + 2, tl.maximum(b + 0.5, 0.0), mask=live)


@triton.jit
def sh_color_backward(grad_ptr, sh_ptr, v_ptr, g_sh_ptr, g_v_ptr, P, K, COEFFS: tl.constexpr, BLOCK: tl.constexpr):
    """∂L/∂sh (P, K, 3; zero beyond COEFFS) and ∂L/∂v (P, 3) from ∂L/∂colour (P, 3): the clamp passes
    the gradient where Σ + 0.5 ≥ 0 (as torch's clamp_min); d̂ = v/|v| carries ∂/∂d̂ as (I − d̂d̂ᵀ)/|v|."""
    p = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = p < P
    vx, vy, vz, norm, x, y, z = _direction(v_ptr, p, live)
    r = x * 0.0
    g = x * 0.0
    b = x * 0.0
    for k in tl.static_range(COEFFS):   # the forward's sums again, for the clamp's mask
        basis, _, _, _ = _basis(k, x, y, z)
        base = sh_ptr + (p * K + k) * 3
        r += basis * tl.load(base, mask=live, other=0.0)
        g += basis * tl.load(base + 1, mask=live, other=0.0)
        b += basis * tl.load(base + 2, mask=live, other=0.0)
    gr = tl.where(r + 0.5 >= 0.0, tl.load(grad_ptr + 3 * p, mask=live, other=0.0), 0.0)
    gg = tl.where(g + 0.5 >= 0.0, tl.load(grad_ptr + 3 * p + 1, mask=live, other=0.0), 0.0)
    gb = tl.where(b + 0.5 >= 0.0, tl.load(grad_ptr + 3 * p + 2, mask=live, other=0.0), 0.0)
    dx = x * 0.0
    dy = x * 0.0
    dz = x * 0.0
    for k in tl.static_range(COEFFS):
        basis, bx, by, bz = _basis(k, x, y, z)
        base = sh_ptr + (p * K + k) * 3
        out = g_sh_ptr + (p * K + k) * 3
        tl.store(out, basis * gr, mask=live)
        tl.store(out + 1, basis * gg, mask=live)
        tl.store(out + 2, basis * gb, mask=live)
        g_basis = (tl.load(base, mask=live, other=0.0) * gr + tl.load(base + 1, mask=live, other=0.0) * gg
                   + tl.load(base + 2, mask=live, other=0.0) * gb)
        dx += g_basis * bx
        dy += g_basis * by
        dz += g_basis * bz
    # normalize's backward: (g − d̂ (d̂·g)) / |v| (|v| clamped at 1e-12 passes g/1e-12, as torch)
    along = x * dx + y * dy + z * dz
    small = tl.sqrt(vx * vx + vy * vy + vz * vz) < 1e-12
    tl.store(g_v_ptr + 3 * p, tl.where(small, dx, dx - x * along) / norm, mask=live)
    tl.store(g_v_ptr + 3 * p + 1, tl.where(small, dy, dy - y * along) / norm, mask=live)
    tl.store(g_v_ptr + 3 * p + 2, tl.where(small, dz, dz - z * along) / norm, mask=live)


# --- the neural frame of a view (twin: core/splat/neural.py view_tensors; fused CPU op:
# csrc/prepare_kernels.cpp neural_prep): M = S⁻¹Rᵀ, m_cam = M R_cam, o' = M (o − μ),
# w_cam = ω0 W1 R_cam, c = ω0 (W1 (o − μ)/max s + b1), 1/max s

@triton.jit
def _rotation(quats_ptr, p, live):
    """R(q̂) (row-major, 9 values) of primitives p's q̂ = q/|q| (|q| at least 1e-12, as torch's
    normalize), and q̂, |q|."""
    q0 = tl.load(quats_ptr + 4 * p, mask=live, other=1.0)
    q1 = tl.load(quats_ptr + 4 * p + 1, mask=live, other=0.0)
    q2 = tl.load(quats_ptr + 4 * p + 2, mask=live, other=0.0)
    q3 = tl.load(quats_ptr + 4 * p + 3, mask=live, other=0.0)
    qnorm = tl.maximum(tl.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3), 1e-12)
    w = q0 / qnorm
    x = q1 / qnorm
    y = q2 / qnorm
    z = q3 / qnorm
    return ((1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
             2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
             2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)), (w, x, y, z), qnorm)


@triton.jit
def _store_rotation_backward(g_quats_ptr, p, live, qn, qnorm, g):
    """∂q of primitives p from ∂R (g, row-major: g[3i + j] = ∂R[i][j]) through R(q̂)
    (csrc/pair_kernels.h rotmat_backward) and q̂ = q/|q|."""
    w, x, y, z = qn
    gw = 2.0 * (-z * g[1] + y * g[2] + z * g[3] - x * g[5] - y * g[6] + x * g[7])
    gx = 2.0 * (y * g[1] + z * g[2] + y * g[3] - 2.0 * x * g[4] - w * g[5] + z * g[6] + w * g[7] - 2.0 * x * g[8])
    gy = 2.0 * (-2.0 * y * g[0] + x * g[1] + w * g[2] + x * g[3] + z * g[5] - w * g[6] + z * g[7] - 2.0 * y * g[8])
    gz = 2.0 * (-2.0 * z * g[0] - w * g[1] + x * g[2] + w * g[3] - 2.0 * z * g[4] + y * g[5] + x * g[6] + y * g[7])
    dot = gw * w + gx * x + gy * y + gz * z
    tl.store(g_quats_ptr + 4 * p, (gw - w * dot) / qnorm, mask=live)
    tl.store(g_quats_ptr + 4 * p + 1, (gx - x * dot) / qnorm, mask=live)
    tl.store(g_quats_ptr + 4 * p + 2, (gy - y * dot) / qnorm, mask=live)
    tl.store(g_quats_ptr + 4 * p + 3, (gz - z * dot) / qnorm, mask=live)


@triton.jit
def _frame(p, live, means_ptr, log_scales_ptr, quats_ptr, view_ptr):
    """One lane per primitive: R (9), q̂ (4), |q|, the log-scales, 1/s (3), max s, rel = o − μ (3)."""
    R, qn, qnorm = _rotation(quats_ptr, p, live)
    l0 = tl.load(log_scales_ptr + 3 * p, mask=live, other=0.0)
    l1 = tl.load(log_scales_ptr + 3 * p + 1, mask=live, other=0.0)
    l2 = tl.load(log_scales_ptr + 3 * p + 2, mask=live, other=0.0)
    smax = tl.exp(tl.maximum(tl.maximum(l0, l1), l2))
    rel = (tl.load(view_ptr) - tl.load(means_ptr + 3 * p, mask=live, other=0.0),
           tl.load(view_ptr + 1) - tl.load(means_ptr + 3 * p + 1, mask=live, other=0.0),
           tl.load(view_ptr + 2) - tl.load(means_ptr + 3 * p + 2, mask=live, other=0.0))
    return R, qn, qnorm, (l0, l1, l2), (tl.exp(-l0), tl.exp(-l1), tl.exp(-l2)), smax, rel


@triton.jit
def neural_prep_forward(means_ptr, log_scales_ptr, quats_ptr, w1_ptr, b1_ptr, view_ptr, m_cam_ptr, o_ell_ptr,
                        w_cam_ptr, c_ptr, inv_smax_ptr, P, N, NP: tl.constexpr, BLOCK: tl.constexpr):
    """view = (o (3), R_cam (3×3 row-major), ω0): the neural primitives' per-view tensors, one lane each
    (the units on a second axis of NP ≥ N lanes)."""
    p = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = p < P
    R, _, _, _, inv_s, smax, rel = _frame(p, live, means_ptr, log_scales_ptr, quats_ptr, view_ptr)
    for i in tl.static_range(3):
        # row i of M = S⁻¹Rᵀ: M[i][j] = R[j][i] / s_i
        m0 = R[i] * inv_s[i]
        m1 = R[3 + i] * inv_s[i]
        m2 = R[6 + i] * inv_s[i]
        for j in tl.static_range(3):
            rc0 = tl.load(view_ptr + 3 + j)
            rc1 = tl.load(view_ptr + 6 + j)
            rc2 = tl.load(view_ptr + 9 + j)
            tl.store(m_cam_ptr + 9 * p + 3 * i + j, m0 * rc0 + m1 * rc1 + m2 * rc2, mask=live)
        tl.store(o_ell_ptr + 3 * p + i, m0 * rel[0] + m1 * rel[1] + m2 * rel[2], mask=live)
    omega0 = tl.load(view_ptr + 12)
    k = tl.arange(0, NP)
    unit = live[:, None] & (k[None, :] < N)
    row = p[:, None] * N + k[None, :]
    w0 = omega0 * tl.load(w1_ptr + 3 * row, mask=unit, other=0.0)
    w1 = omega0 * tl.load(w1_ptr + 3 * row + 1, mask=unit, other=0.0)
    w2 = omega0 * tl.load(w1_ptr + 3 * row + 2, mask=unit, other=0.0)
    for j in tl.static_range(3):
        tl.store(w_cam_ptr + 3 * row + j, w0 * tl.load(view_ptr + 3 + j) + w1 * tl.load(view_ptr + 6 + j)
                 + w2 * tl.load(view_ptr + 9 + j), mask=unit)
    c = (w0 * (rel[0] / smax)[:, None] + w1 * (rel[1] / smax)[:, None] + w2 * (rel[2] / smax)[:, None]
         + omega0 * tl.load(b1_ptr + row, mask=unit, other=0.0))
    tl.store(c_ptr + row, c, mask=unit)
    tl.store(inv_smax_ptr + p, 1.0 / smax, mask=live)


@triton.jit
def _units_backward(j: tl.constexpr, gc, rel_j, smax, omega0, row, unit, g_w_cam_ptr, w1_ptr, view_ptr, g_w1_ptr):
    """Component j of the units' gradients: stores ∂W1[:, :, j] (w = ω0 W1_k: w_cam_k = w R_cam,
    c_k = w·rel/max s + ω0 b1_k) and returns (w_kj rel_j (for ∂max s), Σ_k ∂c_k w_kj / max s (∂rel_j))."""
    g_w = (tl.load(g_w_cam_ptr + 3 * row, mask=unit, other=0.0) * tl.load(view_ptr + 3 + 3 * j)
           + tl.load(g_w_cam_ptr + 3 * row + 1, mask=unit, other=0.0) * tl.load(view_ptr + 4 + 3 * j)
           + tl.load(g_w_cam_ptr + 3 * row + 2, mask=unit, other=0.0) * tl.load(view_ptr + 5 + 3 * j)
           + gc * (rel_j / smax)[:, None])
    tl.store(g_w1_ptr + 3 * row + j, omega0 * g_w, mask=unit)
    w = omega0 * tl.load(w1_ptr + 3 * row + j, mask=unit, other=0.0)
    return w * rel_j[:, None], tl.sum(gc * w, axis=1) / smax


@triton.jit
def _frame_backward(i: tl.constexpr, j: tl.constexpr, p, live, g_o_i, rel_j, g_m_cam_ptr, view_ptr):
    """∂M[i][j] = Σ_l ∂m_cam[i][l] R_cam[j][l] + ∂o'_i rel_j (m_cam = M R_cam, o' = M rel)."""
    return (tl.load(g_m_cam_ptr + 9 * p + 3 * i, mask=live, other=0.0) * tl.load(view_ptr + 3 + 3 * j)
            + tl.load(g_m_cam_ptr + 9 * p + 3 * i + 1, mask=live, other=0.0) * tl.load(view_ptr + 4 + 3 * j)
            + tl.load(g_m_cam_ptr + 9 * p + 3 * i + 2, mask=live, other=0.0) * tl.load(view_ptr + 5 + 3 * j)
            + g_o_i * rel_j)


@triton.jit
def neural_prep_backward(g_m_cam_ptr, g_o_ell_ptr, g_w_cam_ptr, g_c_ptr, g_inv_smax_ptr, means_ptr, log_scales_ptr,
                         quats_ptr, w1_ptr, view_ptr, g_means_ptr, g_log_scales_ptr, g_quats_ptr, g_w1_ptr, g_b1_ptr,
                         P, N, NP: tl.constexpr, BLOCK: tl.constexpr):
    """The gradients of (means, log_scales, quats, w1, b1) from those of the forward's outputs (as
    csrc/prepare_kernels.cpp neural_prep_backward): through m_cam = M R_cam and o' = M rel into
    M = S⁻¹Rᵀ, rel = o − μ and the units' w_cam and c; then M into R(q̂) and the scales, max s
    into the largest log-scale (a tie split evenly, as torch's amax), q̂ = q/|q| into q."""
    p = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = p < P
    R, qn, qnorm, logs, inv_s, smax, rel = _frame(p, live, means_ptr, log_scales_ptr, quats_ptr, view_ptr)
    omega0 = tl.load(view_ptr + 12)
    g_o0 = tl.load(g_o_ell_ptr + 3 * p, mask=live, other=0.0)
    g_o1 = tl.load(g_o_ell_ptr + 3 * p + 1, mask=live, other=0.0)
    g_o2 = tl.load(g_o_ell_ptr + 3 * p + 2, mask=live, other=0.0)
    k = tl.arange(0, NP)
    unit = live[:, None] & (k[None, :] < N)
    row = p[:, None] * N + k[None, :]
    gc = tl.load(g_c_ptr + row, mask=unit, other=0.0)
    tl.store(g_b1_ptr + row, omega0 * gc, mask=unit)
    wr0, u0 = _units_backward(0, gc, rel[0], smax, omega0, row, unit, g_w_cam_ptr, w1_ptr, view_ptr, g_w1_ptr)
    wr1, u1 = _units_backward(1, gc, rel[1], smax, omega0, row, unit, g_w_cam_ptr, w1_ptr, view_ptr, g_w1_ptr)
    wr2, u2 = _units_backward(2, gc, rel[2], smax, omega0, row, unit, g_w_cam_ptr, w1_ptr, view_ptr, g_w1_ptr)
    g_smax = (-tl.load(g_inv_smax_ptr + p, mask=live, other=0.0) - tl.sum(gc * (wr0 + wr1 + wr2), axis=1)) / (smax * smax)
    # rel = o − μ: ∂μ_j = −∂rel_j, ∂rel_j = Σ_i M[i][j] ∂o'_i + the units'
    tl.store(g_means_ptr + 3 * p, -(R[0] * inv_s[0] * g_o0 + R[1] * inv_s[1] * g_o1 + R[2] * inv_s[2] * g_o2 + u0),
             mask=live)
    tl.store(g_means_ptr + 3 * p + 1, -(R[3] * inv_s[0] * g_o0 + R[4] * inv_s[1] * g_o1 + R[5] * inv_s[2] * g_o2 + u1),
             mask=live)
    tl.store(g_means_ptr + 3 * p + 2, -(R[6] * inv_s[0] * g_o0 + R[7] * inv_s[1] * g_o1 + R[8] * inv_s[2] * g_o2 + u2),
             mask=live)
    # M[i][j] = R[j][i] / s_i: ∂R[j][i] = ∂M[i][j] / s_i, ∂(1/s_i) = Σ_j ∂M[i][j] R[j][i]
    m00 = _frame_backward(0, 0, p, live, g_o0, rel[0], g_m_cam_ptr, view_ptr)
    m01 = _frame_backward(0, 1, p, live, g_o0, rel[1], g_m_cam_ptr, view_ptr)
    m02 = _frame_backward(0, 2, p, live, g_o0, rel[2], g_m_cam_ptr, view_ptr)
    m10 = _frame_backward(1, 0, p, live, g_o1, rel[0], g_m_cam_ptr, view_ptr)
    m11 = _frame_backward(1, 1, p, live, g_o1, rel[1], g_m_cam_ptr, view_ptr)
    m12 = _frame_backward(1, 2, p, live, g_o1, rel[2], g_m_cam_ptr, view_ptr)
    m20 = _frame_backward(2, 0, p, live, g_o2, rel[0], g_m_cam_ptr, view_ptr)
    m21 = _frame_backward(2, 1, p, live, g_o2, rel[1], g_m_cam_ptr, view_ptr)
    m22 = _frame_backward(2, 2, p, live, g_o2, rel[2], g_m_cam_ptr, view_ptr)
    g_inv0 = m00 * R[0] + m01 * R[3] + m02 * R[6]
    g_inv1 = m10 * R[1] + m11 * R[4] + m12 * R[7]
    g_inv2 = m20 * R[2] + m21 * R[5] + m22 * R[8]
    lmax = tl.maximum(tl.maximum(logs[0], logs[1]), logs[2])
    ties = (logs[0] == lmax).to(smax.dtype) + (logs[1] == lmax).to(smax.dtype) + (logs[2] == lmax).to(smax.dtype)
    share = g_smax * smax / ties
    tl.store(g_log_scales_ptr + 3 * p, -g_inv0 * inv_s[0] + tl.where(logs[0] == lmax, share, 0.0), mask=live)
    tl.store(g_log_scales_ptr + 3 * p + 1, -g_inv1 * inv_s[1] + tl.where(logs[1] == lmax, share, 0.0), mask=live)
    tl.store(g_log_scales_ptr + 3 * p + 2, -g_inv2 * inv_s[2] + tl.where(logs[2] == lmax, share, 0.0), mask=live)
    # R(q̂) (csrc/pair_kernels.h rotmat_backward; g[3j + i] = ∂R[j][i]), then q̂ = q/|q|
    g0 = m00 * inv_s[0]
    g1 = m10 * inv_s[1]
    g2 = m20 * inv_s[2]
    g3 = m01 * inv_s[0]
    g4 = m11 * inv_s[1]
    g5 = m21 * inv_s[2]
    g6 = m02 * inv_s[0]
    g7 = m12 * inv_s[1]
    g8 = m22 * inv_s[2]
    _store_rotation_backward(g_quats_ptr, p, live, qn, qnorm, (g0, g1, g2, g3, g4, g5, g6, g7, g8))


# --- the Gaussians' EWA projection (twin: core/splat/gaussian.py ewa_view; fused CPU op:
# csrc/prepare_kernels.cpp gaussian_prep): mean2d, the conic of J W Σ Wᵀ Jᵀ + 0.3 I, its (a, b, c)

@triton.jit
def _ewa(p, live, means_cam_ptr, log_scales_ptr, quats_ptr, view_ptr):
    """One lane per splat: the camera-space centre, the clamped Jacobian point and J (4 values), R(q̂),
    q̂, |q|, s, rot = W R, rs = rot diag(s) and t = J rs (2 × 3); view = (W row-major (9), fx, fy,
    cx, cy, near, the Jacobian point's clamp lo_x, hi_x, lo_y, hi_y)."""
    x = tl.load(means_cam_ptr + 3 * p, mask=live, other=0.0)
    y = tl.load(means_cam_ptr + 3 * p + 1, mask=live, other=0.0)
    z = tl.load(means_cam_ptr + 3 * p + 2, mask=live, other=1.0)
    fx = tl.load(view_ptr + 9)
    fy = tl.load(view_ptr + 10)
    near = tl.load(view_ptr + 13)
    zs = tl.where(z > near, z, 1.0)
    tx = zs * tl.minimum(tl.maximum(x / zs, tl.load(view_ptr + 14)), tl.load(view_ptr + 15))
    ty = zs * tl.minimum(tl.maximum(y / zs, tl.load(view_ptr + 16)), tl.load(view_ptr + 17))
    j0 = fx / zs
    j1 = -fx * tx / (zs * zs)
    j2 = fy / zs
    j3 = -fy * ty / (zs * zs)
    R, qn, qnorm = _rotation(quats_ptr, p, live)
    s0, s1, s2 = _scales(log_scales_ptr, p, live)
    rot = _times_w(view_ptr, R)
    rs = (rot[0] * s0, rot[1] * s1, rot[2] * s2, rot[3] * s0, rot[4] * s1, rot[5] * s2,
          rot[6] * s0, rot[7] * s1, rot[8] * s2)
    t = (j0 * rs[0] + j1 * rs[6], j0 * rs[1] + j1 * rs[7], j0 * rs[2] + j1 * rs[8],
         j2 * rs[3] + j3 * rs[6], j2 * rs[4] + j3 * rs[7], j2 * rs[5] + j3 * rs[8])
    return (x, y, z, zs, tx, ty), (j0, j1, j2, j3), R, qn, qnorm, (s0, s1, s2), rot, rs, t


@triton.jit
def _scales(log_scales_ptr, p, live):
    """s = exp(ℓ) of primitives p."""
    return (tl.exp(tl.load(log_scales_ptr + 3 * p, mask=live, other=0.0)),
            tl.exp(tl.load(log_scales_ptr + 3 * p + 1, mask=live, other=0.0)),
            tl.exp(tl.load(log_scales_ptr + 3 * p + 2, mask=live, other=0.0)))


@triton.jit
def _world_to_camera(view_ptr):
    """W, the view's world-to-camera rotation (the first 9 values of `view`, row-major)."""
    return (tl.load(view_ptr), tl.load(view_ptr + 1), tl.load(view_ptr + 2), tl.load(view_ptr + 3),
            tl.load(view_ptr + 4), tl.load(view_ptr + 5), tl.load(view_ptr + 6), tl.load(view_ptr + 7),
            tl.load(view_ptr + 8))


@triton.jit
def _times_w(view_ptr, R):
    """W R (row-major) with W the view's world-to-camera rotation."""
    w00, w01, w02, w10, w11, w12, w20, w21, w22 = _world_to_camera(view_ptr)
    return (w00 * R[0] + w01 * R[3] + w02 * R[6], w00 * R[1] + w01 * R[4] + w02 * R[7], w00 * R[2] + w01 * R[5] + w02 * R[8],
            w10 * R[0] + w11 * R[3] + w12 * R[6], w10 * R[1] + w11 * R[4] + w12 * R[7], w10 * R[2] + w11 * R[5] + w12 * R[8],
            w20 * R[0] + w21 * R[3] + w22 * R[6], w20 * R[1] + w21 * R[4] + w22 * R[7], w20 * R[2] + w21 * R[5] + w22 * R[8])


@triton.jit
def _covariance(t):
    """(a, b, c) of t tᵀ + 0.3 I (3DGS's blur) and its determinant a c − b²."""
    a = t[0] * t[0] + t[1] * t[1] + t[2] * t[2] + 0.3
    b = t[0] * t[3] + t[1] * t[4] + t[2] * t[5]
    c = t[3] * t[3] + t[4] * t[4] + t[5] * t[5] + 0.3
    return a, b, c, a * c - b * b


@triton.jit
def gaussian_prep_forward(means_cam_ptr, log_scales_ptr, quats_ptr, view_ptr, mean2d_ptr, conic_ptr, cov_ptr,
                          bounds_ptr, visible_ptr, P, width, height, BLOCK: tl.constexpr):
    """mean2d (P, 2), conic (P, 3) and the covariance's (a, b, c) (P, 3) of the splats (EWA, 3DGS's
    0.3 px² blur); and (no gradient) their 3σ pixel boxes (P, 4) int32, clipped to the image, and
    visibility (P,) int8: beyond the near plane, a positive-definite covariance and a box in the
    image (twin: core/splat/gaussian.py splat_bounds, with IEEE roots and divisions as torch's)."""
    p = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = p < P
    centre, _, _, _, _, _, _, _, t = _ewa(p, live, means_cam_ptr, log_scales_ptr, quats_ptr, view_ptr)
    x, y, z, zs, _, _ = centre
    a, b, c, det = _covariance(t)
    tl.store(conic_ptr + 3 * p, c / det, mask=live)
    tl.store(conic_ptr + 3 * p + 1, -b / det, mask=live)
    tl.store(conic_ptr + 3 * p + 2, a / det, mask=live)
    tl.store(cov_ptr + 3 * p, a, mask=live)
    tl.store(cov_ptr + 3 * p + 1, b, mask=live)
    tl.store(cov_ptr + 3 * p + 2, c, mask=live)
    mx = tl.load(view_ptr + 9) * x / zs + tl.load(view_ptr + 11)
    my = tl.load(view_ptr + 10) * y / zs + tl.load(view_ptr + 12)
    tl.store(mean2d_ptr + 2 * p, mx, mask=live)
    tl.store(mean2d_ptr + 2 * p + 1, my, mask=live)
    # the box: 3 √λ_max of (a, b, c), rounded up to whole pixels
    lam_max = 0.5 * (a + c) + _sqrt_ieee(tl.maximum(0.25 * (a - c) * (a - c) + b * b, 0.0))
    radius = tl.math.ceil(3.0 * _sqrt_ieee(lam_max))
    big = (tl.maximum(width, height) + 1).to(x.dtype)
    x0 = tl.maximum(tl.minimum(tl.maximum(_box_side(mx - radius, mx, True), -big), big).to(tl.int32), 0)
    y0 = tl.maximum(tl.minimum(tl.maximum(_box_side(my - radius, my, True), -big), big).to(tl.int32), 0)
    x1 = tl.minimum(tl.minimum(tl.maximum(_box_side(mx, mx + radius, False), -big), big).to(tl.int32), width - 1)
    y1 = tl.minimum(tl.minimum(tl.maximum(_box_side(my, my + radius, False), -big), big).to(tl.int32), height - 1)
    visible = (z > tl.load(view_ptr + 13)) & (det > 0.0) & (x1 >= x0) & (y1 >= y0)
    tl.store(bounds_ptr + 4 * p, x0, mask=live)
    tl.store(bounds_ptr + 4 * p + 1, y0, mask=live)
    tl.store(bounds_ptr + 4 * p + 2, x1, mask=live)
    tl.store(bounds_ptr + 4 * p + 3, y1, mask=live)
    tl.store(visible_ptr + p, visible.to(tl.int8), mask=live)


@triton.jit
def gaussian_prep_backward(g_mean2d_ptr, g_conic_ptr, g_cov_ptr, means_cam_ptr, log_scales_ptr, quats_ptr, view_ptr,
                           g_means_cam_ptr, g_log_scales_ptr, g_quats_ptr, P, BLOCK: tl.constexpr):
    """The gradients of (means_cam, log_scales, quats) from those of (mean2d, conic, (a, b, c)), as
    csrc/prepare_kernels.cpp gaussian_prep_backward (which has no (a, b, c) gradient: there they
    only bound the splats; here they enter as they do in the twin)."""
    p = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = p < P
    centre, J, R, qn, qnorm, s, rot, rs, t = _ewa(p, live, means_cam_ptr, log_scales_ptr, quats_ptr, view_ptr)
    x, y, z, zs, tx, ty = centre
    a, b, c, det = _covariance(t)
    # conic = (c, −b, a)/det, det = a c − b²
    gc0 = tl.load(g_conic_ptr + 3 * p, mask=live, other=0.0)
    gc1 = tl.load(g_conic_ptr + 3 * p + 1, mask=live, other=0.0)
    gc2 = tl.load(g_conic_ptr + 3 * p + 2, mask=live, other=0.0)
    g_det = -(gc0 * c - gc1 * b + gc2 * a) / (det * det)
    g_a = gc2 / det + g_det * c + tl.load(g_cov_ptr + 3 * p, mask=live, other=0.0)
    g_b = -gc1 / det - 2.0 * b * g_det + tl.load(g_cov_ptr + 3 * p + 1, mask=live, other=0.0)
    g_c = gc0 / det + g_det * a + tl.load(g_cov_ptr + 3 * p + 2, mask=live, other=0.0)
    # (a, b, c) of t tᵀ
    gt0 = 2.0 * g_a * t[0] + g_b * t[3]
    gt1 = 2.0 * g_a * t[1] + g_b * t[4]
    gt2 = 2.0 * g_a * t[2] + g_b * t[5]
    gt3 = g_b * t[0] + 2.0 * g_c * t[3]
    gt4 = g_b * t[1] + 2.0 * g_c * t[4]
    gt5 = g_b * t[2] + 2.0 * g_c * t[5]
    # t = J rs, J = [[j0, 0, j1], [0, j2, j3]]
    j0, j1, j2, j3 = J
    g_j0 = gt0 * rs[0] + gt1 * rs[1] + gt2 * rs[2]
    g_j1 = gt0 * rs[6] + gt1 * rs[7] + gt2 * rs[8]
    g_j2 = gt3 * rs[3] + gt4 * rs[4] + gt5 * rs[5]
    g_j3 = gt3 * rs[6] + gt4 * rs[7] + gt5 * rs[8]
    g_rs = (j0 * gt0, j0 * gt1, j0 * gt2, j2 * gt3, j2 * gt4, j2 * gt5,
            j1 * gt0 + j3 * gt3, j1 * gt1 + j3 * gt4, j1 * gt2 + j3 * gt5)
    # rs = rot diag(s), rot = W R(q̂), s = exp(ℓ)
    for j in tl.static_range(3):
        g_s = g_rs[j] * rot[j] + g_rs[3 + j] * rot[3 + j] + g_rs[6 + j] * rot[6 + j]
        tl.store(g_log_scales_ptr + 3 * p + j, g_s * s[j], mask=live)
    _store_rotation_backward(g_quats_ptr, p, live, qn, qnorm, _times_w_transposed(view_ptr, g_rs, s))
    # J = [[fx/zs, 0, −fx tx/zs²], [0, fy/zs, −fy ty/zs²]], tx = zs clamp(x/zs), mean2d = f x/zs + c
    fx = tl.load(view_ptr + 9)
    fy = tl.load(view_ptr + 10)
    lo_x = tl.load(view_ptr + 14)
    hi_x = tl.load(view_ptr + 15)
    lo_y = tl.load(view_ptr + 16)
    hi_y = tl.load(view_ptr + 17)
    zz = zs * zs
    g2x = tl.load(g_mean2d_ptr + 2 * p, mask=live, other=0.0)
    g2y = tl.load(g_mean2d_ptr + 2 * p + 1, mask=live, other=0.0)
    g_tx = -fx * g_j1 / zz
    g_ty = -fy * g_j3 / zz
    g_zs = -fx * g_j0 / zz + 2.0 * fx * tx * g_j1 / (zz * zs) - fy * g_j2 / zz + 2.0 * fy * ty * g_j3 / (zz * zs)
    r_x = x / zs
    r_y = y / zs
    g_zs += tl.minimum(tl.maximum(r_x, lo_x), hi_x) * g_tx + tl.minimum(tl.maximum(r_y, lo_y), hi_y) * g_ty
    g_rx = tl.where((r_x >= lo_x) & (r_x <= hi_x), zs * g_tx, 0.0)   # the clamp passes at equality
    g_ry = tl.where((r_y >= lo_y) & (r_y <= hi_y), zs * g_ty, 0.0)
    g_zs -= (g_rx * x + fx * x * g2x + g_ry * y + fy * y * g2y) / zz
    tl.store(g_means_cam_ptr + 3 * p, g_rx / zs + fx * g2x / zs, mask=live)
    tl.store(g_means_cam_ptr + 3 * p + 1, g_ry / zs + fy * g2y / zs, mask=live)
    tl.store(g_means_cam_ptr + 3 * p + 2, tl.where(z > tl.load(view_ptr + 13), g_zs, 0.0), mask=live)


@triton.jit
def _times_w_transposed(view_ptr, g_rs, s):
    """∂R = Wᵀ (∂rs diag(s)) (row-major), from rs = W R diag(s)."""
    w00, w01, w02, w10, w11, w12, w20, w21, w22 = _world_to_camera(view_ptr)
    return ((w00 * g_rs[0] + w10 * g_rs[3] + w20 * g_rs[6]) * s[0], (w00 * g_rs[1] + w10 * g_rs[4] + w20 * g_rs[7]) * s[1],
            (w00 * g_rs[2] + w10 * g_rs[5] + w20 * g_rs[8]) * s[2],
            (w01 * g_rs[0] + w11 * g_rs[3] + w21 * g_rs[6]) * s[0], (w01 * g_rs[1] + w11 * g_rs[4] + w21 * g_rs[7]) * s[1],
            (w01 * g_rs[2] + w11 * g_rs[5] + w21 * g_rs[8]) * s[2],
            (w02 * g_rs[0] + w12 * g_rs[3] + w22 * g_rs[6]) * s[0], (w02 * g_rs[1] + w12 * g_rs[4] + w22 * g_rs[7]) * s[1],
            (w02 * g_rs[2] + w12 * g_rs[5] + w22 * g_rs[8]) * s[2])


# --- the neural primitives' pixel bounds (no gradient; twin: core/splat/view.py ellipsoid_bounds)

@triton.jit
def _sqrt_ieee(x):
    """√x rounded as IEEE (as torch's); float32 needs the _rn form, float64's is IEEE already."""
    if x.dtype == tl.float32:
        return tl.sqrt_rn(x)
    else:
        return tl.sqrt(x)


@triton.jit
def _div_ieee(a, b):
    """a / b rounded as IEEE (as torch's); float32 needs the _rn form, float64's is IEEE already."""
    if a.dtype == tl.float32:
        return tl.div_rn(a, b)
    else:
        return a / b


@triton.jit
def _box_side(lo, hi, low_side: tl.constexpr):
    """conic_box's integer side: the first (low_side) or last pixel centre j + 0.5 in [lo, hi], NaN → −1."""
    if low_side:
        side = tl.math.ceil(lo - 0.5)
    else:
        side = tl.math.floor(hi - 0.5)
    return tl.where(side != side, -1.0, side)


@triton.jit
def neural_bounds(means_cam_ptr, log_scales_ptr, quats_ptr, view_ptr, bounds_ptr, visible_ptr, P, width, height,
                  BLOCK: tl.constexpr):
    """bounds (P, 4) int32 and visible (P,) int8 of the bounding ellipsoids B(μ, R, s): the box of the
    dual conic C* = K (μμᵀ − Σ) Kᵀ (camera frame, Σ = rs rsᵀ, rs = W R diag(s)), the whole image
    for an ellipsoid the near plane cuts, clipped to the image; visible: some of it beyond the near
    plane and its box not empty. view = (W (9), fx, fy, cx, cy, near)."""
    p = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = p < P
    x = tl.load(means_cam_ptr + 3 * p, mask=live, other=0.0)
    y = tl.load(means_cam_ptr + 3 * p + 1, mask=live, other=0.0)
    z = tl.load(means_cam_ptr + 3 * p + 2, mask=live, other=0.0)
    R, _, _ = _rotation(quats_ptr, p, live)
    s0, s1, s2 = _scales(log_scales_ptr, p, live)
    rot = _times_w(view_ptr, R)
    r00 = rot[0] * s0
    r01 = rot[1] * s1
    r02 = rot[2] * s2
    r10 = rot[3] * s0
    r11 = rot[4] * s1
    r12 = rot[5] * s2
    r20 = rot[6] * s0
    r21 = rot[7] * s1
    r22 = rot[8] * s2
    # A = μμᵀ − Σ (the entries the dual's rows 0, 1 and 2 need)
    a00 = x * x - (r00 * r00 + r01 * r01 + r02 * r02)
    a11 = y * y - (r10 * r10 + r11 * r11 + r12 * r12)
    sigma22 = r20 * r20 + r21 * r21 + r22 * r22
    a22 = z * z - sigma22
    a02 = x * z - (r00 * r20 + r01 * r21 + r02 * r22)
    a12 = y * z - (r10 * r20 + r11 * r21 + r12 * r22)
    fx = tl.load(view_ptr + 9)
    fy = tl.load(view_ptr + 10)
    cx = tl.load(view_ptr + 11)
    cy = tl.load(view_ptr + 12)
    near = tl.load(view_ptr + 13)
    # C* = K A Kᵀ, K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
    d22 = a22
    d02 = fx * a02 + cx * a22
    d12 = fy * a12 + cy * a22
    d00 = fx * (fx * a00 + cx * a02) + cx * (fx * a02 + cx * a22)
    d11 = fy * (fy * a11 + cy * a12) + cy * (fy * a12 + cy * a22)
    # the tangent lines u = const: C*_00 − 2u C*_02 + u² C*_22 = 0 (likewise v)
    # (IEEE square roots and divisions, as torch's: a box side is a rounding of these)
    root_u = _sqrt_ieee(tl.maximum(d02 * d02 - d00 * d22, 0.0))
    root_v = _sqrt_ieee(tl.maximum(d12 * d12 - d11 * d22, 0.0))
    u_a = _div_ieee(d02 + root_u, d22)
    u_b = _div_ieee(d02 - root_u, d22)
    v_a = _div_ieee(d12 + root_v, d22)
    v_b = _div_ieee(d12 - root_v, d22)
    big = (tl.maximum(width, height) + 1).to(x.dtype)
    x0 = tl.minimum(tl.maximum(_box_side(tl.minimum(u_a, u_b), tl.maximum(u_a, u_b), True), -big), big)
    y0 = tl.minimum(tl.maximum(_box_side(tl.minimum(v_a, v_b), tl.maximum(v_a, v_b), True), -big), big)
    x1 = tl.minimum(tl.maximum(_box_side(tl.minimum(u_a, u_b), tl.maximum(u_a, u_b), False), -big), big)
    y1 = tl.minimum(tl.maximum(_box_side(tl.minimum(v_a, v_b), tl.maximum(v_a, v_b), False), -big), big)
    z_ext = _sqrt_ieee(sigma22)
    in_front = z - z_ext > near
    x0 = tl.maximum(tl.where(in_front, x0.to(tl.int32), 0), 0)
    y0 = tl.maximum(tl.where(in_front, y0.to(tl.int32), 0), 0)
    x1 = tl.minimum(tl.where(in_front, x1.to(tl.int32), width - 1), width - 1)
    y1 = tl.minimum(tl.where(in_front, y1.to(tl.int32), height - 1), height - 1)
    visible = (z + z_ext > near) & (x1 >= x0) & (y1 >= y0)
    tl.store(bounds_ptr + 4 * p, x0, mask=live)
    tl.store(bounds_ptr + 4 * p + 1, y0, mask=live)
    tl.store(bounds_ptr + 4 * p + 2, x1, mask=live)
    tl.store(bounds_ptr + 4 * p + 3, y1, mask=live)
    tl.store(visible_ptr + p, visible.to(tl.int8), mask=live)
