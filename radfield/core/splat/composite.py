"""Front-to-back compositing (paper eq. 4) of (pixel, primitive, α) pairs, with early termination.

    C = Σ_i c_i α_i T_i,   T_i = Π_{j<i} (1 − α_j)   over a pixel's primitives in depth order,

and a pixel stops at the first pair whose inclusion would take its transmittance below t_min (that
pair and every later one are left out, as 3DGS and the fused kernels do).

`composite_pairs` is the one implementation of these rules on flat pairs: the renderer's readable
torch twin (`composite_view` below, which feeds it depth chunks of pairs evaluated as blocks) and
the retraining teacher (edit/retrain.py: `teacher_render`, `opacity_from`, whose pairs come from
masked quadrature) both call it. The fused C++ view kernels (core/backends/csrc/view_kernels.cpp)
implement the same rules per tile; the quadrature reference (core/render/reference.py) keeps its own
per-pixel loop on purpose: the tests compare the two.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch


class Composited(NamedTuple):
    """The pairs after compositing, every per-pair field in `order` (by pixel, then depth rank)."""
    order: torch.Tensor      # (N,) the permutation of the input pairs into composite order
    pixel: torch.Tensor      # (N,) the pairs' pixel (or ray) ids, = pixel[order]
    weight: torch.Tensor     # (N,) T_before · α of each pair, 0 where not included (alpha's dtype)
    included: torch.Tensor   # (N,) bool: composited, i.e. before its pixel terminated
    log_t: torch.Tensor      # (n_pixels,) float64 log-transmittance after these pairs


def composite_pairs(pixel: torch.Tensor, rank: torch.Tensor, alpha: torch.Tensor, log_t: torch.Tensor,
                    t_min: float) -> Composited:
    """Composite pairs (pixel id, primitive rank, α) (N,) of one batch front to back (eq. 4).

    rank: the pair's position in depth order (a pixel's pairs composite in increasing rank; each
        (pixel, rank) at most once). log_t: (n_pixels,) float64 log-transmittance each pixel already
        has from earlier batches (zeros for the first), so depth-ordered batches chain; a pixel that
        terminated (one of its pairs not `included`) must be left out of later batches by the
        caller, as `composite_view` does (log_t counts included pairs only, so a faint later pair
        would pass the test again). t_min: early termination threshold on transmittance; 0
        composites every pair (no termination).
    The caller accumulates its own per-pair quantities: Σ weight·c over `pixel` with c taken in
    `order` (colour, depth)."""
    span = int(rank.max()) + 1 if rank.numel() else 1
    order = torch.argsort(pixel * span + rank)                   # by pixel, then depth
    pixel, alpha = pixel[order], alpha[order]
    log_t_before, log_1m_alpha = _log_transmittance_before(pixel, alpha, log_t)
    log_t_min = math.log(t_min) if t_min > 0 else -math.inf
    included = (log_t_before + log_1m_alpha >= log_t_min).detach()
    weight = (alpha * torch.exp(log_t_before).to(alpha.dtype)) * included
    log_t = log_t.index_add(0, pixel, log_1m_alpha * included)
    return Composited(order, pixel, weight, included, log_t)


def _log_transmittance_before(pixel: torch.Tensor, alpha: torch.Tensor, log_t: torch.Tensor):
    """For pairs sorted by (pixel, depth): (log T before each pair = the pixel's log T from earlier
    batches + the exclusive segmented cumsum of log(1 − α), log(1 − α)). float64: a running sum over
    a million pairs would lose the per-pixel values to cancellation in float32."""
    log_1m_alpha = torch.log1p(-alpha.double())
    csum = torch.cumsum(log_1m_alpha, 0) - log_1m_alpha              # exclusive running sum
    first = torch.ones_like(pixel, dtype=torch.bool)
    first[1:] = pixel[1:] != pixel[:-1]
    seg = torch.cumsum(first, 0) - 1
    seg_start = torch.nonzero(first).squeeze(1)
    return log_t[pixel] + csum - csum[seg_start][seg], log_1m_alpha


# --- the renderer's torch twin: pairs of a view in depth chunks ---------------------------------

def composite_view(kernel, view, bounds, colors, depth, intrinsics, height, width, max_pairs, t_min):
    """The readable torch twin of the fused view kernel: (Σ w c (H, W, 3), Σ w z (H, W), T (H, W),
    (evaluated pairs, composited pairs, terminated pixels)) for primitives in depth order.

    The pixels of each primitive's bounds (x0, y0, x1, y1) become (primitive, pixel) pairs,
    evaluated by `kernel(u, v, intrinsics, *view)` in depth-ordered chunks of about `max_pairs`
    (pixels that terminated drop out of later chunks) and composited by `composite_pairs`."""
    device, dtype = colors.device, colors.dtype
    x0, y0, x1, y1 = bounds.unbind(-1)
    bw = x1 - x0 + 1
    counts = bw * (y1 - y0 + 1)
    padded = _padded_sizes(counts)

    n_pix = height * width
    log_t = torch.zeros(n_pix, device=device, dtype=torch.float64)   # log transmittance, included pairs
    done = torch.zeros(n_pix, device=device, dtype=torch.bool)        # pixels that terminated early
    acc_color = torch.zeros(n_pix, 3, device=device, dtype=dtype)
    acc_depth = torch.zeros(n_pix, device=device, dtype=dtype)
    n_pairs = n_contrib = 0
    for lo, hi in _chunks(counts, max_pairs):
        # within a depth chunk, primitives of similar footprint are evaluated as dense blocks
        # (primitive × its bounding-box pixels): parameters broadcast instead of being gathered per pair
        ranks, pix, alpha = [], [], []
        for size in torch.unique(padded[lo:hi]).tolist():
            sel = lo + torch.nonzero(padded[lo:hi] == size).squeeze(1)
            k = torch.arange(size, device=device)
            row = y0[sel, None] + k // bw[sel, None]
            col = x0[sel, None] + k % bw[sel, None]
            block_pix = torch.where(k < counts[sel, None], row * width + col, -1)   # -1: padding
            live = (block_pix >= 0) & ~done[block_pix.clamp_min(0)]
            n_pairs += int(live.sum())
            block_alpha = kernel(col.to(dtype) + 0.5, row.to(dtype) + 0.5, intrinsics, *(t[sel] for t in view))
            p, q = torch.nonzero(live & (block_alpha > 0), as_tuple=True)
            ranks.append(sel[p])
            pix.append(block_pix[p, q])
            alpha.append(block_alpha[p, q])
        ranks, pix, alpha = torch.cat(ranks), torch.cat(pix), torch.cat(alpha)
        out = composite_pairs(pix, ranks, alpha, log_t, t_min)
        ranks, pix, weight, log_t = ranks[out.order], out.pixel, out.weight, out.log_t
        acc_color = acc_color.index_add(0, pix, weight[:, None] * colors[ranks])
        acc_depth = acc_depth.index_add(0, pix, weight * depth[ranks])
        done[pix[~out.included]] = True
        n_contrib += int(out.included.sum())
    transmittance = torch.exp(log_t).to(dtype).reshape(height, width)
    return (acc_color.reshape(height, width, 3), acc_depth.reshape(height, width), transmittance,
            (n_pairs, n_contrib, int(done.sum())))


def _chunks(counts: torch.Tensor, max_pairs: int):
    """Consecutive ranges [lo, hi) of depth-sorted primitives holding about max_pairs pairs each
    (a primitive larger than max_pairs gets a chunk of its own)."""
    if counts.numel() == 0:
        return []
    ends = torch.cumsum(counts, 0)
    chunk = ((ends - counts) // max_pairs).tolist()
    out, lo = [], 0
    for i in range(1, len(chunk) + 1):
        if i == len(chunk) or chunk[i] != chunk[lo]:
            out.append((lo, i))
            lo = i
    return out


def _padded_sizes(counts: torch.Tensor) -> torch.Tensor:
    """Block size of each primitive: its pixel count rounded up a ×1.25 ladder (≤ 25% padding,
    and few distinct sizes, so few blocks)."""
    top = max(int(counts.max()) if counts.numel() else 1, 1)
    ladder = [4]
    while ladder[-1] < top:
        ladder.append(max(ladder[-1] + 1, int(ladder[-1] * 1.25)))
    ladder = torch.tensor(ladder, device=counts.device)
    return ladder[torch.searchsorted(ladder, counts)]
