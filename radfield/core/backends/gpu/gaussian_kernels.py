"""The Triton kernels of the Gaussian view (core/backends/gpu/views.py joins them into one
autograd op): per-tile front-to-back compositing and its backward, as 3DGS rasterises on a GPU.

Imported only when a view is drawn on the "triton" backend (it imports triton; with
TRITON_INTERPRET=1 set before that import the same kernels run on CPU tensors, which is how the
tests check them against the torch twin without a GPU).

One program per 16×16 tile, one lane per pixel (BLOCK = 256). The inputs are every splat's, index
r: bounds (P, 4) int32 inclusive pixel boxes, mean2d (P, 2), conic (P, 3), opacity (P,), colour
(P, 3), depth (P,); a tile reads the indices entries[offsets[t]:offsets[t + 1]], its visible splats
front to back (gpu.bin_tiles). consts = (t_min, α_min, α_max) in the inputs'
dtype, so a float64 view compares at float64 with the twin's thresholds.

Forward (paper eq. 4; the twin's rules, core/splat/composite.py): a pixel evaluates a splat only
inside its box; α = min(α_max, o·exp(power)), a miss when α < α_min or power > 0; the first pair
that would take T below t_min is not composited and ends the pixel. Each pixel keeps Σ w c, Σ w z,
its final T and `last`, the list position after its last composited pair; each tile its counts of
(evaluated, composited, terminated) pairs.

Backward (3DGS): each pixel walks its list back to front from `last`, recovering T_i = T_{i+1}/(1 − α_i)
and the suffix S_i = Σ_{j>i} (g_C·c_j + g_D z_j) α_j T_j + g_T T_final, so that
∂L/∂α_i = (g_C·c_i + g_D z_i) T_i − S_i/(1 − α_i); the splat's gradients are summed over the
tile's pixels eight at a time and added to the primitive's with one relaxed 8-lane atomic add per
eight (tiles.py: _add_sums). The forward counts its live pixels once per CHUNK list entries.
"""

from __future__ import annotations

import triton
import triton.language as tl

from radfield.core.backends.gpu.tiles import (CHUNK, _add_sums, _alive, _composite, _pick, _store_tile, _tile_pixels,
                                             _uncomposite, _upstream)

SIDE = 16   # tile side in pixels (one program per tile, one lane per pixel)


@triton.jit
def _splat(r, px, py, bounds_ptr, mean_ptr, conic_ptr, opacity_ptr, alpha_min, alpha_max):
    """Splat r at the pixels: (in its box, the conic's terms dx, dy, power, the unclamped
    o·exp(power), α, hit = composited unless the pixel terminates)."""
    x0 = tl.load(bounds_ptr + 4 * r)
    y0 = tl.load(bounds_ptr + 4 * r + 1)
    x1 = tl.load(bounds_ptr + 4 * r + 2)
    y1 = tl.load(bounds_ptr + 4 * r + 3)
    in_box = (px >= x0) & (px <= x1) & (py >= y0) & (py <= y1)
    mx = tl.load(mean_ptr + 2 * r)
    my = tl.load(mean_ptr + 2 * r + 1)
    ca = tl.load(conic_ptr + 3 * r)
    cb = tl.load(conic_ptr + 3 * r + 1)
    cc = tl.load(conic_ptr + 3 * r + 2)
    o = tl.load(opacity_ptr + r)
    dx = (px.to(mx.dtype) + 0.5) - mx          # pixel centres, as the twin's u = x + 0.5
    dy = (py.to(mx.dtype) + 0.5) - my
    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
    raw = o * tl.exp(tl.minimum(power, 0.0))
    alpha = tl.minimum(raw, alpha_max)
    hit = in_box & (alpha >= alpha_min) & (power <= 0.0)
    return in_box, dx, dy, power, raw, alpha, hit


@triton.jit
def gaussian_forward(offsets_ptr, entries_ptr, bounds_ptr, mean_ptr, conic_ptr, opacity_ptr, color_ptr, depth_ptr,
                     consts_ptr, out_color_ptr, out_depth_ptr, out_trans_ptr, last_ptr, counts_ptr,
                     height, width, tiles_x, SIDE: tl.constexpr):
    tile = tl.program_id(0)
    px, py, pix, inside = _tile_pixels(tile, tiles_x, height, width, SIDE)
    t_min = tl.load(consts_ptr)
    alpha_min = tl.load(consts_ptr + 1)
    alpha_max = tl.load(consts_ptr + 2)
    dtype = consts_ptr.dtype.element_ty
    trans = tl.full([SIDE * SIDE], 1.0, dtype)
    acc_r = tl.zeros([SIDE * SIDE], dtype)
    acc_g = tl.zeros([SIDE * SIDE], dtype)
    acc_b = tl.zeros([SIDE * SIDE], dtype)
    acc_z = tl.zeros([SIDE * SIDE], dtype)
    last = tl.zeros([SIDE * SIDE], tl.int32)
    done = inside == 0                            # pixels outside the image never composite
    n_pairs = tl.zeros([SIDE * SIDE], tl.int32)
    n_composited = tl.zeros([SIDE * SIDE], tl.int32)
    n_terminated = tl.zeros([SIDE * SIDE], tl.int32)
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    j = start
    alive = _alive(done)
    while (j < end) & (alive > 0):               # front to back, until every pixel terminated
        chunk_end = tl.minimum(j + CHUNK, end)
        while j < chunk_end:
            r = tl.load(entries_ptr + j)
            in_box, dx, dy, power, raw, alpha, hit = _splat(r, px, py, bounds_ptr, mean_ptr, conic_ptr, opacity_ptr,
                                                            alpha_min, alpha_max)
            live = in_box & (done == 0)
            (trans, done, last, acc_r, acc_g, acc_b, acc_z, n_pairs, n_composited, n_terminated) = _composite(
                alpha, hit & live, live, r, j, start, t_min, color_ptr, depth_ptr, trans, done, last,
                acc_r, acc_g, acc_b, acc_z, n_pairs, n_composited, n_terminated)
            j += 1
        alive = _alive(done)
    _store_tile(tile, pix, inside, trans, last, acc_r, acc_g, acc_b, acc_z, n_pairs, n_composited, n_terminated,
                out_color_ptr, out_depth_ptr, out_trans_ptr, last_ptr, counts_ptr)


@triton.jit
def gaussian_backward(offsets_ptr, entries_ptr, bounds_ptr, mean_ptr, conic_ptr, opacity_ptr, color_ptr, depth_ptr,
                      consts_ptr, trans_ptr, last_ptr, g_color_ptr, g_depth_ptr, g_trans_ptr,
                      d_mean_ptr, d_conic_ptr, d_opacity_ptr, d_color_ptr, d_depth_ptr,
                      height, width, tiles_x, SIDE: tl.constexpr):
    tile = tl.program_id(0)
    px, py, pix, inside = _tile_pixels(tile, tiles_x, height, width, SIDE)
    alpha_min = tl.load(consts_ptr + 1)
    alpha_max = tl.load(consts_ptr + 2)
    trans, last, g_r, g_g, g_b, g_z, suffix = _upstream(pix, inside, trans_ptr, last_ptr, g_color_ptr, g_depth_ptr,
                                                        g_trans_ptr)
    start = tl.load(offsets_ptr + tile)
    lane = tl.arange(0, 8)
    steps = tl.max(last)                          # the longest walk of the tile's pixels
    for step in range(0, steps):
        local = steps - 1 - step                  # back to front
        r = tl.load(entries_ptr + start + local)
        in_box, dx, dy, power, raw, alpha, hit = _splat(r, px, py, bounds_ptr, mean_ptr, conic_ptr, opacity_ptr,
                                                        alpha_min, alpha_max)
        hit = hit & (local < last)                # before `last` every hit was composited
        if tl.sum(hit.to(tl.int32)) > 0:
            trans, g_alpha, suffix, g_cr, g_cg, g_cb, g_cz = _uncomposite(alpha, hit, r, trans, suffix, g_r, g_g, g_b,
                                                                          g_z, color_ptr, depth_ptr)
            # α = min(α_max, o e^power): no gradient through the clamp
            g_raw = tl.where(raw <= alpha_max, g_alpha, 0.0)
            g_power = g_raw * raw
            ca = tl.load(conic_ptr + 3 * r)
            cb = tl.load(conic_ptr + 3 * r + 1)
            cc = tl.load(conic_ptr + 3 * r + 2)
            # the splat's ten gradients in two sums of eight: colour, depth, opacity, conic; the 2D mean
            # (power's derivative by it, dx = u − μx)
            _add_sums(_pick(lane, d_color_ptr + 3 * r, d_color_ptr + 3 * r + 1, d_color_ptr + 3 * r + 2,
                            d_depth_ptr + r, d_opacity_ptr + r, d_conic_ptr + 3 * r, d_conic_ptr + 3 * r + 1,
                            d_conic_ptr + 3 * r + 2),
                      lane < 8, g_cr, g_cg, g_cb, g_cz, g_raw * tl.exp(tl.minimum(power, 0.0)),
                      g_power * (-0.5 * dx * dx), g_power * (-dx * dy), g_power * (-0.5 * dy * dy))
            zero = tl.zeros_like(g_power)
            _add_sums(d_mean_ptr + 2 * r + lane, lane < 2, g_power * (ca * dx + cb * dy), g_power * (cc * dy + cb * dx),
                      zero, zero, zero, zero, zero, zero)
