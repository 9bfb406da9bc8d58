"""The tile walk the Triton view kernels share (gaussian_kernels.py, neural_kernels.py): a 16×16
tile's pixels, one front-to-back compositing step of their lists and the tile's stores (forward),
and the backward's upstream gradients and one back-to-front step. What differs between the kinds
is only the pair (α and its own gradients); the compositing rules are the twin's
(core/splat/composite.py), and gaussian_kernels.py's docstring states them and the backward's
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


CHUNK = tl.constexpr(32)   # list entries between two counts of the live pixels (_alive)


@triton.jit
def _alive(done):
    """How many of the tile's pixels still composite: the walk stops at 0. Counted once a CHUNK of
    list entries, not each entry: a count is a reduction over the tile, its warps wait for one
    another, and a finished pixel only idles its lane (3DGS counts once per batch of 256 splats)."""
    return tl.sum((done == 0).to(tl.int32))


@triton.jit
def _composite(alpha, hit, live, r, j, start, t_min, color_ptr, depth_ptr, trans, done, last,
               acc_r, acc_g, acc_b, acc_z, n_pairs, n_composited, n_terminated):
    """List entry j (primitive r) at the tile's pixels, front to back: `live` pixels evaluated the pair,
    `hit` ones have α ≥ α_min; the first pair that would take T below t_min is not composited and
    ends the pixel. Returns the pixels' state after it (T, done, last, Σ w c, Σ w z, the counts)."""
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
    return trans, done, last, acc_r, acc_g, acc_b, acc_z, n_pairs, n_composited, n_terminated


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
def _uncomposite(alpha, hit, r, trans, suffix, g_r, g_g, g_b, g_z, color_ptr, depth_ptr):
    """Pair r, back to front, at the pixels where it was composited (`hit`): T_i = T_{i+1}/(1 − α_i),
    ∂L/∂α_i = (g_C·c_i + g_D z_i) T_i − S_i/(1 − α_i). Returns (T_i, ∂L/∂α_i, S_{i−1}) and the
    pixels' terms of the pair's colour and depth gradients, g_C w and g_D w (the kernels sum them
    with the kind's own, _add_sums)."""
    one_minus = 1.0 - alpha
    trans = tl.where(hit, trans / one_minus, trans)     # T_i, before this pair
    w = tl.where(hit, alpha * trans, 0.0)
    shade = (g_r * tl.load(color_ptr + 3 * r) + g_g * tl.load(color_ptr + 3 * r + 1)
             + g_b * tl.load(color_ptr + 3 * r + 2) + g_z * tl.load(depth_ptr + r))
    g_alpha = tl.where(hit, shade * trans - suffix / one_minus, 0.0)
    suffix += w * shade
    return trans, g_alpha, suffix, g_r * w, g_g * w, g_b * w, g_z * w


@triton.jit
def _pick(lane, v0, v1, v2, v3, v4, v5, v6, v7):
    """(8,): v_k at lane k (scalars: pointers or numbers)."""
    return tl.where(lane < 4, tl.where(lane < 2, tl.where(lane == 0, v0, v1), tl.where(lane == 2, v2, v3)),
                    tl.where(lane < 6, tl.where(lane == 4, v4, v5), tl.where(lane == 6, v6, v7)))


@triton.jit
def _add_sums(ptrs, mask, v0, v1, v2, v3, v4, v5, v6, v7):
    """Eight per-pixel gradient terms summed over the tile and added at ptrs (8,) where `mask`: one
    reduction of the eight stacked in each lane's registers and one 8-lane atomic add, where a sum
    each would make the tile's warps wait for one another eight times (a block-wide reduction
    synchronises through shared memory; gsplat reduces before its atomics for the same reason).
    Relaxed atomics: the sums need no ordering, and the default acq_rel would fence each one."""
    # join adds a last axis, so the first join's pair is the most significant bit of the flat index:
    # pairing v_k with v_(k+4) first puts v_k at lane k
    stacked = tl.join(tl.join(tl.join(v0, v4), tl.join(v2, v6)), tl.join(tl.join(v1, v5), tl.join(v3, v7)))
    sums = tl.sum(tl.reshape(stacked, [v0.shape[0], 8]), axis=0)
    tl.atomic_add(ptrs, sums, mask=mask, sem="relaxed")
