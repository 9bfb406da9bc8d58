"""The Triton kernel of the non-negative density projection (core/backends/gpu/positivity.py
launches it): each masked primitive's (W2, b2) onto the cone ‖W2‖₁ ≤ b2, in place, one lane per
primitive and its UNITS hidden units unrolled. The twin is core/train/positivity.py:
project_nonnegative (its eq. 2): W2' = S_λ(W2), b2' = b2 + λ, λ the root of
‖S_λ(W2)‖₁ = b2 + λ. The twin sorts |W2| and tries each count m of units kept; here each unit k
tries to be the smallest one kept (the m = #{i: |w_i| ≥ |w_k|} of a tie's last place),
λ_k = (Σ_{|w_i| ≥ |w_k|} |w_i| − b2)/(m + 1), valid when the next smaller |w| ≤ λ_k < |w_k|; of
the valid ones the smallest m wins, as the twin's first in its sorted order. Rows inside the cone
to rounding stay as they are; rows with no valid λ (the polar cone) become (0, 0).
"""

from __future__ import annotations

import triton
import triton.language as tl

BLOCK = 128   # primitives a program


@triton.jit
def project_nonnegative(w2_ptr, b2_ptr, mask_ptr, count, UNITS: tl.constexpr, BLOCK: tl.constexpr):
    p = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = p < count
    live = live & (tl.load(mask_ptr + p, mask=live, other=0) != 0)
    b2 = tl.load(b2_ptr + p, mask=live, other=0.0)
    w = ()
    for k in tl.static_range(UNITS):
        w = w + (tl.load(w2_ptr + p * UNITS + k, mask=live, other=0.0),)
    l1 = tl.zeros_like(b2)
    for k in tl.static_range(UNITS):
        l1 += tl.abs(w[k])
    inside = l1 <= b2 + 1e-6 * (tl.abs(b2) + 1.0)     # within rounding of the cone: unchanged
    lam = tl.zeros_like(b2)
    kept = tl.full(b2.shape, UNITS + 1, tl.int32)      # the m of the λ found (UNITS + 1: none yet)
    for k in tl.static_range(UNITS):
        a_k = tl.abs(w[k])
        total = tl.zeros_like(b2)
        m = tl.zeros(b2.shape, tl.int32)
        below = tl.zeros_like(b2)                       # the largest |w| under a_k (0: none)
        for i in tl.static_range(UNITS):
            a_i = tl.abs(w[i])
            ge = a_i >= a_k
            total += tl.where(ge, a_i, 0.0)
            m += ge.to(tl.int32)
            below = tl.where(ge, below, tl.maximum(below, a_i))
        candidate = (total - b2) / (m + 1).to(b2.dtype)
        better = (candidate >= below) & (candidate < a_k) & (m < kept)
        lam = tl.where(better, candidate, lam)
        kept = tl.where(better, m, kept)
    lam = tl.maximum(lam, 0.0)
    polar = (kept > UNITS) & (inside == 0)
    change = live & (inside == 0)
    for k in tl.static_range(UNITS):
        shrunk = tl.maximum(tl.abs(w[k]) - lam, 0.0)
        signed = tl.where(w[k] > 0.0, shrunk, tl.where(w[k] < 0.0, -shrunk, 0.0))
        tl.store(w2_ptr + p * UNITS + k, tl.where(polar, 0.0, signed), mask=change)
    tl.store(b2_ptr + p, tl.where(polar, 0.0, b2 + lam), mask=change)
