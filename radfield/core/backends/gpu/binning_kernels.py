"""The Triton kernels of the tile binning (core/backends/gpu/binning.py launches them; gsplat's
isect_tiles): one lane per primitive.

    tile_counts: each primitive's place in the depth order (place[order[i]] = i) and the number of
                 16×16 tiles its box touches (0 when invisible)
    tile_keys:   after the running sum of those counts (ends), the primitive's keys
                 tile · P + place, one per tile its box touches, at ends − touched onward
"""

from __future__ import annotations

import triton
import triton.language as tl

BLOCK = 128   # primitives per program


@triton.jit
def _tile_box(bounds_ptr, p, live, SIDE: tl.constexpr):
    """The tiles (tx0, ty0, tx1, ty1) that primitives p's pixel box touches."""
    tx0 = tl.load(bounds_ptr + 4 * p, mask=live, other=0) // SIDE
    ty0 = tl.load(bounds_ptr + 4 * p + 1, mask=live, other=0) // SIDE
    tx1 = tl.load(bounds_ptr + 4 * p + 2, mask=live, other=0) // SIDE
    ty1 = tl.load(bounds_ptr + 4 * p + 3, mask=live, other=0) // SIDE
    return tx0, ty0, tx1, ty1


@triton.jit
def tile_counts(bounds_ptr, visible_ptr, order_ptr, place_ptr, touched_ptr, P, SIDE: tl.constexpr,
                BLOCK: tl.constexpr):
    """Lane i: primitive p = order[i] gets place[p] = i and touched[p] (int64) = its box's tiles."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = i < P
    p = tl.load(order_ptr + i, mask=live, other=0)
    tx0, ty0, tx1, ty1 = _tile_box(bounds_ptr, p, live, SIDE)
    seen = tl.load(visible_ptr + p, mask=live, other=0) != 0
    tl.store(place_ptr + p, i.to(tl.int64), mask=live)
    tl.store(touched_ptr + p, tl.where(seen, (tx1 - tx0 + 1) * (ty1 - ty0 + 1), 0).to(tl.int64), mask=live)


@triton.jit
def tile_keys(bounds_ptr, place_ptr, touched_ptr, ends_ptr, keys_ptr, P, tiles_x, SIDE: tl.constexpr,
              BLOCK: tl.constexpr):
    """Lane p writes the keys tile · P + place[p] of the tiles its box touches, row by row, at
    ends[p] − touched[p] onward."""
    p = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = p < P
    tx0, ty0, tx1, _ = _tile_box(bounds_ptr, p, live, SIDE)
    touched = tl.load(touched_ptr + p, mask=live, other=0)
    start = tl.load(ends_ptr + p, mask=live, other=0) - touched
    place = tl.load(place_ptr + p, mask=live, other=0)
    across = tl.maximum(tx1 - tx0 + 1, 1)
    for k in range(0, tl.max(touched, axis=0)):
        tile = (ty0 + k // across) * tiles_x + tx0 + k % across
        tl.store(keys_ptr + start + k, tile.to(tl.int64) * P + place, mask=live & (k < touched))
