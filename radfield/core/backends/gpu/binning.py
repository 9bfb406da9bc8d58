"""The tile binning of a view on the Triton backend (torch ops on the device): every visible
primitive × the 16×16 tiles its box touches, as sorted keys (tile, depth rank), and each tile's
range of primitive indices, front to back (gsplat's isect_tiles and isect_offset_encode)."""

from __future__ import annotations

import torch

from radfield.core.backends.gpu.launch import TILE


def bin_tiles(bounds: torch.Tensor, visible: torch.Tensor, order: torch.Tensor, height: int,
              width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The tile lists of P boxes (bounds (P, 4) inclusive pixel boxes inside the image where
    `visible` (P,), anything elsewhere) in the depth order `order` (P,) (every index once, front to
    back): (offsets (tiles + 1,) int32, entries int32), tile t's box indices, front to back, at
    entries[offsets[t]:offsets[t + 1]]. Every (visible box, tile it touches) pair is one key
    tile · P + the box's place in `order`, sorted."""
    device = bounds.device
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    count = max(bounds.shape[0], 1)
    place = torch.empty_like(order)
    place[order] = torch.arange(order.numel(), device=device)
    tx0, ty0, tx1, ty1 = (bounds // TILE).long().unbind(-1)
    across = tx1 - tx0 + 1
    touched = torch.where(visible, across * (ty1 - ty0 + 1), 0)
    pairs = pair_count(touched)
    box = torch.repeat_interleave(torch.arange(bounds.shape[0], device=device), touched, output_size=pairs)
    k = torch.arange(pairs, device=device) - (torch.cumsum(touched, 0) - touched)[box]
    tile = (ty0[box] + k // across[box]) * tiles_x + tx0[box] + k % across[box]
    keys, _ = torch.sort(tile * count + place[box])
    # tile t's keys start at the first key ≥ t · P (a search, not a histogram: bincount reads its size)
    starts = torch.arange(tiles_x * tiles_y + 1, device=device) * count
    return torch.searchsorted(keys, starts).to(torch.int32), order[keys % count].to(torch.int32)


def pair_count(touched: torch.Tensor) -> int:
    """The view's one read of the device: how many (tile, primitive) pairs its boxes make, the
    length of the key array to allocate (3DGS and gsplat read the same number)."""
    return int(touched.sum())
