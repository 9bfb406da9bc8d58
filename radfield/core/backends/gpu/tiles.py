"""The tile walk the Triton view kernels share (gaussian_kernels.py, neural_kernels.py): a 16×16
tile's pixels, one front-to-back compositing step of their lists and the tile's stores (forward),
and the backward's upstream gradients and one back-to-front step. What differs between the kinds
is only the pair (α and its own gradients); the compositing rules are the twin's
(core/render/composite.py), and gaussian_kernels.py's docstring states them and the backward's
suffix S.

Imported only with those kernels (it imports triton).
"""

from __future__ import annotations

import triton
import triton.language as tl


@triton.jit
def _tile_pixels(tile, tiles_x, height, width, SIDE: tl.constexpr):
    """The tile's pixel coordinates (x, y), their flat index and whether they are in the image."""
    k = tl.arange(0, SIDE * SIDE)
    px = (tile % tiles_x) * SIDE + k % SIDE
    py = (tile // tiles_x) * SIDE + k // SIDE
    inside = (px < width) & (py < height)
    return px, py, py * width + px, inside


@triton.jit
def _composite(alpha, hit, live, r, j, start, t_min, color_ptr, depth_ptr, trans, done, last,
               acc_r, acc_g, acc_b, acc_z, n_pairs, n_composited, n_terminated, alive):
    """List entry j (primitive r) at the tile's pixels, front to back: `live` pixels evaluated the pair,
    `hit` ones have α ≥ α_min; the first pair that would take T below t_min is not composited and
    ends the pixel. Returns the pixels' state after it (T, done, last, Σ w c, Σ w z, the counts,
    the pixels still alive)."""
    after = trans * (1.0 - alpha)
    stop = hit & (after < t_min)              # early termination: this pair is not composited
    take = hit & (stop == 0)
    w = tl.where(take, alpha * trans, 0.0)
    acc_r += w * tl.load(color_ptr + 3 * r)
    acc_g += w * tl.load(color_ptr + 3 * r + 1)
    acc_b += w * tl.load(color_ptr + 3 * r + 2)
    acc_z += w * tl.load(depth_ptr + r)
    trans = tl.where(take, after, trans)
    last = tl.where(take, (j - start + 1).to(tl.int32), last)
    done = done | stop
    n_pairs += live.to(tl.int32)
    n_composited += take.to(tl.int32)
    n_terminated += stop.to(tl.int32)
    alive -= tl.sum(stop.to(tl.int32))
    return trans, done, last, acc_r, acc_g, acc_b, acc_z, n_pairs, n_composited, n_terminated, alive


@triton.jit
def _store_tile(tile, pix, inside, trans, last, acc_r, acc_g, acc_b, acc_z, n_pairs, n_composited, n_terminated,
                out_color_ptr, out_depth_ptr, out_trans_ptr, last_ptr, counts_ptr):
    """The pixels' Σ w c, Σ w z, final T and `last`, and the tile's (evaluated, composited,
    terminated) pair counts."""
    tl.store(out_color_ptr + 3 * pix, acc_r, mask=inside)
    tl.store(out_color_ptr + 3 * pix + 1, acc_g, mask=inside)
    tl.store(out_color_ptr + 3 * pix + 2, acc_b, mask=inside)
    tl.store(out_depth_ptr + pix, acc_z, mask=inside)
    tl.store(out_trans_ptr + pix, trans, mask=inside)
    tl.store(last_ptr + pix, last, mask=inside)
    tl.store(counts_ptr + 3 * tile, tl.sum(n_pairs))
    tl.store(counts_ptr + 3 * tile + 1, tl.sum(n_composited))
    tl.store(counts_ptr + 3 * tile + 2, tl.sum(n_terminated))


@triton.jit
def _upstream(pix, inside, trans_ptr, last_ptr, g_color_ptr, g_depth_ptr, g_trans_ptr):
    """The backward's start at each pixel: its final T and `last`, the upstream gradients of its
    colour and depth, and the suffix S = g_T T_final (the later pairs are added on the way)."""
    trans = tl.load(trans_ptr + pix, mask=inside, other=1.0)
    last = tl.load(last_ptr + pix, mask=inside, other=0)
    g_r = tl.load(g_color_ptr + 3 * pix, mask=inside, other=0.0)
    g_g = tl.load(g_color_ptr + 3 * pix + 1, mask=inside, other=0.0)
    g_b = tl.load(g_color_ptr + 3 * pix + 2, mask=inside, other=0.0)
    g_z = tl.load(g_depth_ptr + pix, mask=inside, other=0.0)
    suffix = tl.load(g_trans_ptr + pix, mask=inside, other=0.0) * trans
    return trans, last, g_r, g_g, g_b, g_z, suffix


@triton.jit
def _uncomposite(alpha, hit, r, trans, suffix, g_r, g_g, g_b, g_z, color_ptr, depth_ptr, d_color_ptr, d_depth_ptr):
    """Pair r, back to front, at the pixels where it was composited (`hit`): T_i = T_{i+1}/(1 − α_i),
    the colour's and depth's gradients added to the pair's, ∂L/∂α_i = (g_C·c_i + g_D z_i) T_i −
    S_i/(1 − α_i). Returns (T_i, ∂L/∂α_i, S_{i−1})."""
    one_minus = 1.0 - alpha
    trans = tl.where(hit, trans / one_minus, trans)     # T_i, before this pair
    w = tl.where(hit, alpha * trans, 0.0)
    shade = (g_r * tl.load(color_ptr + 3 * r) + g_g * tl.load(color_ptr + 3 * r + 1)
             + g_b * tl.load(color_ptr + 3 * r + 2) + g_z * tl.load(depth_ptr + r))
    g_alpha = tl.where(hit, shade * trans - suffix / one_minus, 0.0)
    suffix += w * shade
    tl.atomic_add(d_color_ptr + 3 * r, tl.sum(g_r * w))
    tl.atomic_add(d_color_ptr + 3 * r + 1, tl.sum(g_g * w))
    tl.atomic_add(d_color_ptr + 3 * r + 2, tl.sum(g_b * w))
    tl.atomic_add(d_depth_ptr + r, tl.sum(g_z * w))
    return trans, g_alpha, suffix
