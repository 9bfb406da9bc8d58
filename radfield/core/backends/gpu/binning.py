"""The tile binning of a view on the Triton backend: every visible primitive × the 16×16 tiles its
box touches, as sorted keys (tile, depth rank) (binning_kernels.py, then torch.sort), and each
tile's range of primitive indices, front to back (gsplat's isect_tiles and isect_offset_encode)."""

from __future__ import annotations

import torch

from radfield.core.backends.gpu.launch import PREPARE_OPTIONS, TILE, launching


def bin_tiles(bounds: torch.Tensor, visible: torch.Tensor, order: torch.Tensor, height: int,
              width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The tile lists of P boxes (bounds (P, 4) int32 inclusive pixel boxes inside the image where
    `visible` (P,), anything elsewhere) in the depth order `order` (P,) (every index once, front to
    back): (offsets (tiles + 1,) int32, entries int32), tile t's box indices, front to back, at
    entries[offsets[t]:offsets[t + 1]]. Every (visible box, tile it touches) pair is one key
    tile · P + the box's place in `order` (binning_kernels.py), sorted."""
    from radfield.core.backends.gpu import binning_kernels as K

    device, count = bounds.device, bounds.shape[0]
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    if count == 0:
        return (torch.zeros(tiles_x * tiles_y + 1, dtype=torch.int32, device=device),
                torch.zeros(0, dtype=torch.int32, device=device))
    bounds, order = bounds.to(torch.int32).contiguous(), order.contiguous()
    place, touched = torch.empty_like(order), torch.empty(count, dtype=torch.int64, device=device)
    grid = (-(-count // K.BLOCK),)
    with launching():
        K.tile_counts[grid](bounds, visible.to(torch.int8), order, place, touched, count, SIDE=TILE, BLOCK=K.BLOCK,
                            **PREPARE_OPTIONS)
    ends = torch.cumsum(touched, 0)
    keys = torch.empty(pair_count(ends), dtype=torch.int64, device=device)
    with launching():
        K.tile_keys[grid](bounds, place, touched, ends, keys, count, tiles_x, SIDE=TILE, BLOCK=K.BLOCK,
                          **PREPARE_OPTIONS)
    keys, _ = torch.sort(keys)
    # tile t's keys start at the first key ≥ t · P (a search, not a histogram: bincount reads its size)
    starts = torch.arange(tiles_x * tiles_y + 1, device=device) * count
    return torch.searchsorted(keys, starts).to(torch.int32), order[keys % count].to(torch.int32)


def pair_count(ends: torch.Tensor) -> int:
    """The view's one read of the device: how many (tile, primitive) pairs its boxes make (the last
    of the running sum `ends`), the length of the key array to allocate (3DGS and gsplat read the
    same number)."""
    return int(ends[-1])
