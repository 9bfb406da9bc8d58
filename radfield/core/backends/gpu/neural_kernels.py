"""The Triton kernels of the neural view (core/backends/gpu/views.py joins them into one autograd
op): the closed-form line integral of a neural primitive per (pixel, primitive) pair, hard-edged
or windowed (core/splat/kernels.py: neural_optical_depth, windowed_optical_depth), composited per
16×16 tile front to back, and its backward walking each pixel's list back to front.

The same tile walk as gaussian_kernels.py (tiles.py; gaussian_kernels.py's docstring says the
compositing rules and the backward's suffix); what differs is the pair: one lane per pixel, its
hidden units unrolled (UNITS = N, a constant of the compiled kernel), so that a lane keeps its
pixel's units in registers and a unit's sum never crosses lanes. The maths and its backward are those
of the fused CPU kernels (core/backends/csrc/pair_kernels.h: ChordTile), which follow the torch
twin's autograd (clamps pass the gradient at equality, torch.maximum splits it at a tie).
Inputs (P, ...), read through the tile lists as the Gaussians' (gaussian_kernels.py): m_cam (P, 9) =
S⁻¹Rᵀ R_cam, o_ell (P, 3), w_cam (P, N, 3) = ω0 W1 R_cam, c (P, N), w2 (P, N), b2 (P,), inv_smax (P,); intrinsics (fx, fy, cx, cy, near); consts (t_min, α_min, α_max, 1)
in the inputs' dtype (the 1 makes the series' rational coefficients in that dtype, not float32).
"""

from __future__ import annotations

import triton
import triton.language as tl

from radfield.core.backends.gpu.tiles import (CHUNK, _add_sums, _alive, _composite, _pick, _store_tile, _tile_pixels,
                                             _uncomposite, _upstream)


@triton.jit
def _directions(px, py, intrinsics_ptr):
    """Unit camera-space directions through the pixel centres and the near plane's ray distance
    (splat/view.py: camera_directions)."""
    fx = tl.load(intrinsics_ptr)
    fy = tl.load(intrinsics_ptr + 1)
    cx = tl.load(intrinsics_ptr + 2)
    cy = tl.load(intrinsics_ptr + 3)
    near = tl.load(intrinsics_ptr + 4)
    xn = ((px.to(fx.dtype) + 0.5) - cx) / fx
    yn = ((py.to(fx.dtype) + 0.5) - cy) / fy
    norm = tl.sqrt(xn * xn + yn * yn + 1.0)
    return xn / norm, yn / norm, 1.0 / norm, near * norm


@triton.jit
def _box(r, px, py, bounds_ptr):
    x0 = tl.load(bounds_ptr + 4 * r)
    y0 = tl.load(bounds_ptr + 4 * r + 1)
    x1 = tl.load(bounds_ptr + 4 * r + 2)
    y1 = tl.load(bounds_ptr + 4 * r + 3)
    return (px >= x0) & (px <= x1) & (py >= y0) & (py <= y1)


@triton.jit
def _chord(r, d0, d1, d2, l_near, m_ptr, o_ptr, inv_smax_ptr):
    """Step 1 (kernels.py: ray_ellipsoid in the closest-approach form): d' = M d̂, A, ℓ*, p, the
    chord's ends, the near-plane clip, Δ, τ_m, e and κ per pixel."""
    e0 = tl.load(m_ptr + 9 * r) * d0 + tl.load(m_ptr + 9 * r + 1) * d1 + tl.load(m_ptr + 9 * r + 2) * d2
    e1 = tl.load(m_ptr + 9 * r + 3) * d0 + tl.load(m_ptr + 9 * r + 4) * d1 + tl.load(m_ptr + 9 * r + 5) * d2
    e2 = tl.load(m_ptr + 9 * r + 6) * d0 + tl.load(m_ptr + 9 * r + 7) * d1 + tl.load(m_ptr + 9 * r + 8) * d2
    o0 = tl.load(o_ptr + 3 * r)
    o1 = tl.load(o_ptr + 3 * r + 1)
    o2 = tl.load(o_ptr + 3 * r + 2)
    inv_smax = tl.load(inv_smax_ptr + r)
    big_a = e0 * e0 + e1 * e1 + e2 * e2
    l_mid = -(o0 * e0 + o1 * e1 + o2 * e2) / big_a
    p0 = o0 + l_mid * e0
    p1 = o1 + l_mid * e1
    p2 = o2 + l_mid * e2
    h = p0 * p0 + p1 * p1 + p2 * p2
    hit = h < 1.0
    half = tl.sqrt(tl.where(hit, (1.0 - h) / big_a, 1.0))
    l_in_raw = l_mid - half
    l_out = l_mid + half
    l_in = tl.maximum(l_in_raw, l_near)          # camera inside: start at the near plane
    delta = tl.where(hit, tl.maximum(l_out - l_in, 0.0) * inv_smax, 0.0)
    tau_m = 0.5 * (l_in + l_out) * inv_smax
    clip = (l_in - l_in_raw) * inv_smax
    kappa = big_a / (inv_smax * inv_smax)
    return e0, e1, e2, o0, o1, o2, inv_smax, big_a, l_mid, p0, p1, p2, half, l_in_raw, l_in, l_out, delta, tau_m, clip, kappa


@triton.jit
def _sinc(x, sin_x):
    return tl.where(x == 0.0, 1.0, sin_x / tl.where(x == 0.0, 1.0, x))


@triton.jit
def _window_integral(x, sin_x, cos_x, one):
    """W(x) = 2 (sin x − x cos x)/x³, by its series below |x| = 1 (kernels.py: window_integral)."""
    x2 = x * x
    series = 2.0 * one / 3.0 - x2 * (one / 15.0 - x2 * (one / 420.0 - x2 * (one / 22680.0 - x2 * (
        one / 1995840.0 - x2 / 259459200.0))))
    safe = tl.where(tl.abs(x) < 1.0, 1.0, x)
    return tl.where(tl.abs(x) < 1.0, series, 2.0 * (sin_x - safe * cos_x) / (safe * safe * safe))


@triton.jit
def _unit(r, u, d0, d1, d2, delta, tau_m, w_ptr, c_ptr, w2_ptr, UNITS: tl.constexpr):
    """Hidden unit u of primitive r at the pixels: its W2 weight, a = ω·d̂ (ω = ω0 W1 R_cam's row),
    the phase a τ_m + c at the chord's middle, x = a Δ/2, and their cosines and sines."""
    row = r * UNITS + u
    a = tl.load(w_ptr + 3 * row) * d0 + tl.load(w_ptr + 3 * row + 1) * d1 + tl.load(w_ptr + 3 * row + 2) * d2
    phase = a * tau_m + tl.load(c_ptr + row)
    x = 0.5 * a * delta
    return tl.load(w2_ptr + row), a, tl.cos(phase), tl.sin(phase), x, tl.sin(x), tl.cos(x)


@triton.jit
def _optical_depth(r, d0, d1, d2, delta, tau_m, clip, kappa, b2, w_ptr, c_ptr, w2_ptr, one,
                   UNITS: tl.constexpr, WINDOW: tl.constexpr):
    """Step 2: I per pixel (paper eq. 7–8, stable sinc form; or the window's, 1.5 κ [...]), the sum
    in brackets, and each unit's terms the backward reuses: (W2, a, cos φ, sin φ, x, sin x, cos x,
    sinc x, the window's W(x) or sinc x). The units are unrolled (UNITS is the kernel's constant):
    each lane keeps its pixel's units in registers."""
    inner = tl.zeros_like(delta)
    terms = ()
    for u in tl.static_range(UNITS):
        w2, a, cos_p, sin_p, x, sin_x, cos_x = _unit(r, u, d0, d1, d2, delta, tau_m, w_ptr, c_ptr, w2_ptr, UNITS)
        sinc_x = _sinc(x, sin_x)
        if WINDOW:
            win = _window_integral(x, sin_x, cos_x, one)
            inner += w2 * (cos_p * (0.25 * delta * delta * delta) * win
                           + clip * (0.5 * delta * delta) * (cos_p * sinc_x + sin_p * (0.5 * x * win)))
        else:
            win = sinc_x
            inner += w2 * (delta * cos_p * sinc_x)
        terms = terms + ((w2, a, cos_p, sin_p, x, sin_x, cos_x, sinc_x, win),)
    if WINDOW:
        inner += b2 * (delta * delta * delta / 6.0 + clip * (0.5 * delta * delta))
        integral = 1.5 * kappa * inner
    else:
        integral = inner + b2 * delta
    return integral, inner, terms


@triton.jit
def _expm1_neg(depth):
    """expm1(−max(I, 0)) accurately for small I (Kahan: (u − 1)·y/log u, u = e^y; no libdevice)."""
    y = -tl.maximum(depth, 0.0)
    u = tl.exp(y)
    um1 = u - 1.0
    safe = tl.where((u == 1.0) | (um1 == -1.0), 0.5, u)
    return tl.where(u == 1.0, y, tl.where(um1 == -1.0, -1.0, um1 * y / tl.log(safe)))


@triton.jit
def neural_forward(offsets_ptr, entries_ptr, bounds_ptr, intrinsics_ptr, m_ptr, o_ptr, w_ptr, c_ptr, w2_ptr, b2_ptr,
                   inv_smax_ptr, color_ptr, depth_ptr, consts_ptr, out_color_ptr, out_depth_ptr, out_trans_ptr,
                   last_ptr, counts_ptr, height, width, tiles_x,
                   SIDE: tl.constexpr, UNITS: tl.constexpr, WINDOW: tl.constexpr):
    tile = tl.program_id(0)
    px, py, pix, inside = _tile_pixels(tile, tiles_x, height, width, SIDE)
    d0, d1, d2, l_near = _directions(px, py, intrinsics_ptr)
    t_min = tl.load(consts_ptr)
    alpha_min = tl.load(consts_ptr + 1)
    alpha_max = tl.load(consts_ptr + 2)
    one = tl.load(consts_ptr + 3)
    dtype = consts_ptr.dtype.element_ty
    trans = tl.full([SIDE * SIDE], 1.0, dtype)
    acc_r = tl.zeros([SIDE * SIDE], dtype)
    acc_g = tl.zeros([SIDE * SIDE], dtype)
    acc_b = tl.zeros([SIDE * SIDE], dtype)
    acc_z = tl.zeros([SIDE * SIDE], dtype)
    last = tl.zeros([SIDE * SIDE], tl.int32)
    done = inside == 0
    n_pairs = tl.zeros([SIDE * SIDE], tl.int32)
    n_composited = tl.zeros([SIDE * SIDE], tl.int32)
    n_terminated = tl.zeros([SIDE * SIDE], tl.int32)
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    j = start
    alive = _alive(done)
    while (j < end) & (alive > 0):
        chunk_end = tl.minimum(j + CHUNK, end)
        while j < chunk_end:
            r = tl.load(entries_ptr + j)
            live = _box(r, px, py, bounds_ptr) & (done == 0)
            (e0, e1, e2, o0, o1, o2, inv_smax, big_a, l_mid, p0, p1, p2, half, l_in_raw, l_in, l_out, delta, tau_m,
             clip, kappa) = _chord(r, d0, d1, d2, l_near, m_ptr, o_ptr, inv_smax_ptr)
            integral, inner, terms = _optical_depth(r, d0, d1, d2, delta, tau_m, clip, kappa, tl.load(b2_ptr + r),
                                                    w_ptr, c_ptr, w2_ptr, one, UNITS, WINDOW)
            alpha = tl.minimum(-_expm1_neg(integral), alpha_max)          # eq. 9 with the 3DGS clamp
            hit = live & (alpha >= alpha_min) & (delta > 0.0)
            (trans, done, last, acc_r, acc_g, acc_b, acc_z, n_pairs, n_composited, n_terminated) = _composite(
                alpha, hit, live, r, j, start, t_min, color_ptr, depth_ptr, trans, done, last,
                acc_r, acc_g, acc_b, acc_z, n_pairs, n_composited, n_terminated)
            j += 1
        alive = _alive(done)
    _store_tile(tile, pix, inside, trans, last, acc_r, acc_g, acc_b, acc_z, n_pairs, n_composited, n_terminated,
                out_color_ptr, out_depth_ptr, out_trans_ptr, last_ptr, counts_ptr)


@triton.jit
def _unit_sums(ptrs, lane, values, first: tl.constexpr, UNITS: tl.constexpr):
    """Units first … first + 7 of a per-unit gradient (pixel terms `values`, padded to a multiple of
    8) summed over the tile and added at ptrs (8,) = the gradient's entries of those units."""
    _add_sums(ptrs, first + lane < UNITS, values[first], values[first + 1], values[first + 2], values[first + 3],
              values[first + 4], values[first + 5], values[first + 6], values[first + 7])


@triton.jit
def neural_backward(offsets_ptr, entries_ptr, bounds_ptr, intrinsics_ptr, m_ptr, o_ptr, w_ptr, c_ptr, w2_ptr, b2_ptr,
                    inv_smax_ptr, color_ptr, depth_ptr, consts_ptr, trans_ptr, last_ptr, g_color_ptr, g_depth_ptr,
                    g_trans_ptr, d_m_ptr, d_o_ptr, d_w_ptr, d_c_ptr, d_w2_ptr, d_b2_ptr, d_inv_smax_ptr, d_color_ptr,
                    d_depth_ptr, height, width, tiles_x,
                    SIDE: tl.constexpr, UNITS: tl.constexpr, WINDOW: tl.constexpr):
    tile = tl.program_id(0)
    px, py, pix, inside = _tile_pixels(tile, tiles_x, height, width, SIDE)
    d0, d1, d2, l_near = _directions(px, py, intrinsics_ptr)
    lane = tl.arange(0, 8)
    alpha_min = tl.load(consts_ptr + 1)
    alpha_max = tl.load(consts_ptr + 2)
    one = tl.load(consts_ptr + 3)
    trans, last, g_r, g_g, g_b, g_z, suffix = _upstream(pix, inside, trans_ptr, last_ptr, g_color_ptr, g_depth_ptr,
                                                        g_trans_ptr)
    start = tl.load(offsets_ptr + tile)
    steps = tl.max(last)
    for step in range(0, steps):
        local = steps - 1 - step
        r = tl.load(entries_ptr + start + local)
        (e0, e1, e2, o0, o1, o2, inv_smax, big_a, l_mid, p0, p1, p2, half, l_in_raw, l_in, l_out, delta, tau_m, clip,
         kappa) = _chord(r, d0, d1, d2, l_near, m_ptr, o_ptr, inv_smax_ptr)
        b2 = tl.load(b2_ptr + r)
        integral, inner, terms = _optical_depth(r, d0, d1, d2, delta, tau_m, clip, kappa, b2, w_ptr, c_ptr, w2_ptr, one,
                                                UNITS, WINDOW)
        em1 = _expm1_neg(integral)
        alpha = tl.minimum(-em1, alpha_max)
        hit = _box(r, px, py, bounds_ptr) & (alpha >= alpha_min) & (delta > 0.0) & (local < last) & inside
        if tl.sum(hit.to(tl.int32)) > 0:
            # compositing (tiles.py): T_i by division, ∂L/∂α_i, the suffix S, the colour's and depth's terms
            trans, g_alpha, suffix, g_cr, g_cg, g_cb, g_cz = _uncomposite(alpha, hit, r, trans, suffix, g_r, g_g, g_b,
                                                                          g_z, color_ptr, depth_ptr)
            # eq. 9: ∂α/∂I = e^(−I) = 1 + expm1(−I), unless the 0.99 clamp is active
            g_i = tl.where(hit & (-em1 <= alpha_max), g_alpha * (em1 + 1.0), 0.0)
            # step 2 backward, unit by unit (pair_kernels.h: optical_depth_backward / windowed_pixel_backward):
            # the pixels' ∂L/∂τ_m, ∂L/∂Δ, ∂L/∂clip and each unit's terms of ∂L/∂c, ∂L/∂W2, ∂L/∂a
            g_tau = tl.zeros_like(g_i)
            g_c = ()
            g_w2 = ()
            g_a = ()
            if WINDOW:
                gk = g_i * 1.5 * kappa
                d3 = 0.25 * delta * delta * delta
                d2h = 0.5 * delta * delta
                d3_dl = 0.75 * delta * delta
                g_delta = gk * b2 * (0.5 * delta * delta + clip * delta)
                g_clip = gk * b2 * (0.5 * delta * delta)
                g_kappa = g_i * 1.5 * inner
                g_b2 = gk * (delta * delta * delta / 6.0 + clip * (0.5 * delta * delta))
            else:
                g_delta = g_i * b2
                g_clip = tl.zeros_like(g_i)
                g_kappa = tl.zeros_like(g_i)
                g_b2 = g_i * delta
            for u in tl.static_range(UNITS):
                w2, a, cos_p, sin_p, x, sin_x, cos_x, sinc_x, win = terms[u]
                if WINDOW:
                    x2 = x * x
                    small = tl.abs(x) < 1.0
                    safe = tl.where(small, 1.0, x)
                    series = -x * (2.0 * one / 15.0 - x2 * (one / 105.0 - x2 * (one / 3780.0 - x2 * (
                        one / 249480.0 - x2 / 25945920.0))))
                    win_slope = tl.where(small, series, 2.0 * sin_x / (safe * safe) - 3.0 * win / safe)
                    gw = gk * w2
                    j1 = 0.5 * x * win
                    f2 = 0.5 * (win + x * win_slope)
                    cut_term = cos_p * sinc_x + sin_p * j1
                    f = cos_p * d3 * win + clip * d2h * cut_term
                    f_phase = -sin_p * d3 * win + clip * d2h * (cos_p * j1 - sin_p * sinc_x)
                    f_x = cos_p * d3 * win_slope + clip * d2h * (sin_p * f2 - cos_p * j1)
                    f_dl = cos_p * d3_dl * win + clip * delta * cut_term
                    g_phase = gw * f_phase
                    g_x = gw * f_x
                    g_delta += gw * f_dl + 0.5 * g_x * a
                    g_clip += gw * d2h * cut_term
                    g_w2 = g_w2 + (gk * f,)
                else:
                    small = tl.abs(x) < 1e-2
                    safe = tl.where(small, 1.0, x)
                    slope = tl.where(small, x * (x * x / 30.0 - one / 3.0), (cos_x - sinc_x) / safe)
                    gwd = g_i * w2 * delta
                    g_phase = -gwd * sin_p * sinc_x
                    g_x = gwd * cos_p * slope
                    g_delta += g_i * w2 * cos_p * sinc_x + 0.5 * g_x * a
                    g_w2 = g_w2 + (g_i * delta * cos_p * sinc_x,)
                g_tau += g_phase * a
                g_c = g_c + (g_phase,)
                g_a = g_a + (g_phase * tau_m + 0.5 * g_x * delta,)
            if WINDOW:
                g_clip = tl.where(clip == 0.0, 0.0, g_clip)
            zero = tl.zeros_like(g_i)
            for u in tl.static_range(UNITS, -(-UNITS // 8) * 8):    # the units' terms padded to groups of 8
                g_c = g_c + (zero,)
                g_w2 = g_w2 + (zero,)
                g_a = g_a + (zero,)
            g_ax = ()
            g_ay = ()
            g_az = ()
            for u in tl.static_range(len(g_a)):                    # ∂L/∂ω = ∂L/∂a d̂
                g_ax = g_ax + (g_a[u] * d0,)
                g_ay = g_ay + (g_a[u] * d1,)
                g_az = g_az + (g_a[u] * d2,)
            for first in tl.static_range(0, len(g_a), 8):
                row = r * UNITS + first + lane
                _unit_sums(d_c_ptr + row, lane, g_c, first, UNITS)
                _unit_sums(d_w2_ptr + row, lane, g_w2, first, UNITS)
                _unit_sums(d_w_ptr + 3 * row, lane, g_ax, first, UNITS)
                _unit_sums(d_w_ptr + 3 * row + 1, lane, g_ay, first, UNITS)
                _unit_sums(d_w_ptr + 3 * row + 2, lane, g_az, first, UNITS)
            # step 1 backward (pair_kernels.h: chords_backward)
            inv2 = inv_smax * inv_smax
            g_inv = g_delta * (l_out - l_in) + g_tau * 0.5 * (l_in + l_out)
            if WINDOW:
                g_inv += g_clip * (l_in - l_in_raw) - 2.0 * g_kappa * big_a / (inv2 * inv_smax)
            g_length = g_delta * inv_smax
            g_l_in = -g_length + 0.5 * inv_smax * g_tau + g_clip * inv_smax
            g_l_out = g_length + 0.5 * inv_smax * g_tau
            tie = tl.where(l_in_raw == l_near, 0.5 * g_l_in, 0.0)
            g_l_in_raw = tl.where(l_in_raw > l_near, g_l_in, tie) - g_clip * inv_smax
            g_half = g_l_out - g_l_in_raw
            g_s = g_half / (2.0 * half)
            g_h = -g_s / big_a
            g_p0 = 2.0 * g_h * p0
            g_p1 = 2.0 * g_h * p1
            g_p2 = 2.0 * g_h * p2
            g_lmid = g_l_in_raw + g_l_out + g_p0 * e0 + g_p1 * e1 + g_p2 * e2
            g_mid = g_lmid / big_a
            g_big_a = -g_s * (half * half) / big_a - g_mid * l_mid + g_kappa / inv2
            g_e0 = tl.where(hit, l_mid * g_p0 - g_mid * o0 + 2.0 * g_big_a * e0, 0.0)
            g_e1 = tl.where(hit, l_mid * g_p1 - g_mid * o1 + 2.0 * g_big_a * e1, 0.0)
            g_e2 = tl.where(hit, l_mid * g_p2 - g_mid * o2 + 2.0 * g_big_a * e2, 0.0)
            # the primitive's 18 gradients in three sums of eight: colour, depth, b2, 1/max s, o′; M (d_m = g_e d̂ᵀ)
            _add_sums(_pick(lane, d_color_ptr + 3 * r, d_color_ptr + 3 * r + 1, d_color_ptr + 3 * r + 2,
                            d_depth_ptr + r, d_b2_ptr + r, d_inv_smax_ptr + r, d_o_ptr + 3 * r, d_o_ptr + 3 * r + 1),
                      lane < 8, g_cr, g_cg, g_cb, g_cz, g_b2, tl.where(hit, g_inv, 0.0),
                      tl.where(hit, g_p0 - g_mid * e0, 0.0), tl.where(hit, g_p1 - g_mid * e1, 0.0))
            _add_sums(_pick(lane, d_o_ptr + 3 * r + 2, d_m_ptr + 9 * r, d_m_ptr + 9 * r + 1, d_m_ptr + 9 * r + 2,
                            d_m_ptr + 9 * r + 3, d_m_ptr + 9 * r + 4, d_m_ptr + 9 * r + 5, d_m_ptr + 9 * r + 6),
                      lane < 8, tl.where(hit, g_p2 - g_mid * e2, 0.0), g_e0 * d0, g_e0 * d1, g_e0 * d2, g_e1 * d0,
                      g_e1 * d1, g_e1 * d2, g_e2 * d0)
            _add_sums(d_m_ptr + 9 * r + 7 + lane, lane < 2, g_e2 * d1, g_e2 * d2, zero, zero, zero, zero, zero, zero)
