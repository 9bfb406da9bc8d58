"""The Triton kernels of the photometric loss (core/backends/gpu/loss.py joins them into one
autograd op): (1 − λ) L1 + λ D-SSIM of images x, y (B, H, W, C), channel-last, flattened; the
SSIM map with the 11×11 Gaussian window g_u g_v and zero padding 5 ("same", the training loss's).

One lane per image element e = ((b H + i) W + j) C + c, BLOCK a program; the window separably, as
the twin (core/train/losses.py: _photometric): a pass along the rows, then one along the columns.

Forward: the rows pass sums x, y, x², y², xy over its 11 taps of the row (ssim_rows); the
columns pass sums those over its 11 rows into the window moments μx, μy, E[x²], E[y²], E[xy] and
makes the map (Wang et al.)
    S = (2 μx μy + C1)(2 σxy + C2) / ((μx² + μy² + C1)(σx² + σy² + C2)),
σx² = E[x²] − μx², σxy = E[xy] − μx μy, its derivatives by the window sums of x, x², xy,
    A = ∂S/∂μx − 2 μx ∂S/∂σx² − μy ∂S/∂σxy,   B = ∂S/∂σx²,   K = ∂S/∂σxy,
kept for the backward, and each program's sums of S and |x − y| (ssim_columns).
Backward: ∂S̄/∂x_q = (1/n) Σ_p w(p − q) (A_p + 2 x_q B_p + y_q K_p): the (symmetric) window's
two passes again, over A, B and K (adjoint_rows, adjoint_columns), and the L1 term's sign(x − y)
(0 at a tie, as torch's abs).
consts = (C1, C2, (1 − λ)/n, λ/n) in the images' dtype.
"""

from __future__ import annotations

import triton
import triton.language as tl

BLOCK = 1024   # image elements a program
TAPS = tl.constexpr(11)
HALF = tl.constexpr(5)


@triton.jit
def _elements(pid, total, height, width, channels, BLOCK: tl.constexpr):
    """A program's elements e, whether they exist, and their (image, row, column, channel)."""
    e = pid * BLOCK + tl.arange(0, BLOCK)
    c = e % channels
    j = (e // channels) % width
    i = (e // (channels * width)) % height
    return e, e < total, e // (channels * width * height), i, j, c


@triton.jit
def _tap(taps_ptr, k, b, i, j, c, live, height, width, channels, ALONG_ROW: tl.constexpr):
    """Tap k of the window around (i, j): its weight, the element it reads and whether that lies in
    the image (outside: the zero padding)."""
    if ALONG_ROW:
        row = i
        col = j + k - HALF
    else:
        row = i + k - HALF
        col = j
    inside = live & (row >= 0) & (row < height) & (col >= 0) & (col < width)
    return tl.load(taps_ptr + k), ((b * height + row) * width + col) * channels + c, inside


@triton.jit
def ssim_rows(x_ptr, y_ptr, taps_ptr, rows_ptr, total, height, width, channels, BLOCK: tl.constexpr):
    e, live, b, i, j, c = _elements(tl.program_id(0), total, height, width, channels, BLOCK)
    sx = tl.zeros([BLOCK], x_ptr.dtype.element_ty)
    sy = tl.zeros_like(sx)
    sxx = tl.zeros_like(sx)
    syy = tl.zeros_like(sx)
    sxy = tl.zeros_like(sx)
    for k in range(0, TAPS):
        w, q, inside = _tap(taps_ptr, k, b, i, j, c, live, height, width, channels, True)
        xq = tl.load(x_ptr + q, mask=inside, other=0.0)
        yq = tl.load(y_ptr + q, mask=inside, other=0.0)
        sx += w * xq
        sy += w * yq
        sxx += w * (xq * xq)
        syy += w * (yq * yq)
        sxy += w * (xq * yq)
    tl.store(rows_ptr + e, sx, mask=live)
    tl.store(rows_ptr + total + e, sy, mask=live)
    tl.store(rows_ptr + 2 * total + e, sxx, mask=live)
    tl.store(rows_ptr + 3 * total + e, syy, mask=live)
    tl.store(rows_ptr + 4 * total + e, sxy, mask=live)


@triton.jit
def ssim_columns(x_ptr, y_ptr, taps_ptr, consts_ptr, rows_ptr, abk_ptr, sums_ptr, total, height, width, channels,
                 BLOCK: tl.constexpr):
    pid = tl.program_id(0)
    e, live, b, i, j, c = _elements(pid, total, height, width, channels, BLOCK)
    mx = tl.zeros([BLOCK], x_ptr.dtype.element_ty)
    my = tl.zeros_like(mx)
    mxx = tl.zeros_like(mx)
    myy = tl.zeros_like(mx)
    mxy = tl.zeros_like(mx)
    for k in range(0, TAPS):
        w, q, inside = _tap(taps_ptr, k, b, i, j, c, live, height, width, channels, False)
        mx += w * tl.load(rows_ptr + q, mask=inside, other=0.0)
        my += w * tl.load(rows_ptr + total + q, mask=inside, other=0.0)
        mxx += w * tl.load(rows_ptr + 2 * total + q, mask=inside, other=0.0)
        myy += w * tl.load(rows_ptr + 3 * total + q, mask=inside, other=0.0)
        mxy += w * tl.load(rows_ptr + 4 * total + q, mask=inside, other=0.0)
    c1 = tl.load(consts_ptr)
    c2 = tl.load(consts_ptr + 1)
    var_x = mxx - mx * mx
    var_y = myy - my * my
    cov = mxy - mx * my
    n1 = 2.0 * mx * my + c1
    n2 = 2.0 * cov + c2
    d1 = mx * mx + my * my + c1
    d2 = var_x + var_y + c2
    ssim = (n1 * n2) / (d1 * d2)
    ds_dvar = -ssim / d2
    ds_dcov = 2.0 * n1 / (d1 * d2)
    ds_dmu = 2.0 * my * n2 / (d1 * d2) - ssim * (2.0 * mx / d1)
    tl.store(abk_ptr + e, ds_dmu - 2.0 * mx * ds_dvar - my * ds_dcov, mask=live)
    tl.store(abk_ptr + total + e, ds_dvar, mask=live)
    tl.store(abk_ptr + 2 * total + e, ds_dcov, mask=live)
    x = tl.load(x_ptr + e, mask=live, other=0.0)
    y = tl.load(y_ptr + e, mask=live, other=0.0)
    tl.store(sums_ptr + 2 * pid, tl.sum(tl.where(live, ssim, 0.0)))
    tl.store(sums_ptr + 2 * pid + 1, tl.sum(tl.abs(x - y)))


@triton.jit
def _sums_of_three(maps_ptr, taps_ptr, b, i, j, c, live, total, height, width, channels, BLOCK: tl.constexpr,
                   ALONG_ROW: tl.constexpr):
    """The window's pass along the row or the column over three maps (maps[0:n], [n:2n], [2n:3n])."""
    sa = tl.zeros([BLOCK], maps_ptr.dtype.element_ty)
    sb = tl.zeros_like(sa)
    sk = tl.zeros_like(sa)
    for k in range(0, TAPS):
        w, p, inside = _tap(taps_ptr, k, b, i, j, c, live, height, width, channels, ALONG_ROW)
        sa += w * tl.load(maps_ptr + p, mask=inside, other=0.0)
        sb += w * tl.load(maps_ptr + total + p, mask=inside, other=0.0)
        sk += w * tl.load(maps_ptr + 2 * total + p, mask=inside, other=0.0)
    return sa, sb, sk


@triton.jit
def adjoint_rows(taps_ptr, abk_ptr, rows_ptr, total, height, width, channels, BLOCK: tl.constexpr):
    e, live, b, i, j, c = _elements(tl.program_id(0), total, height, width, channels, BLOCK)
    sa, sb, sk = _sums_of_three(abk_ptr, taps_ptr, b, i, j, c, live, total, height, width, channels, BLOCK, True)
    tl.store(rows_ptr + e, sa, mask=live)
    tl.store(rows_ptr + total + e, sb, mask=live)
    tl.store(rows_ptr + 2 * total + e, sk, mask=live)


@triton.jit
def adjoint_columns(x_ptr, y_ptr, taps_ptr, consts_ptr, rows_ptr, g_ptr, out_ptr, total, height, width, channels,
                    BLOCK: tl.constexpr):
    e, live, b, i, j, c = _elements(tl.program_id(0), total, height, width, channels, BLOCK)
    sa, sb, sk = _sums_of_three(rows_ptr, taps_ptr, b, i, j, c, live, total, height, width, channels, BLOCK, False)
    x = tl.load(x_ptr + e, mask=live, other=0.0)
    y = tl.load(y_ptr + e, mask=live, other=0.0)
    d = x - y
    sign = tl.where(d > 0.0, 1.0, tl.where(d < 0.0, -1.0, 0.0))
    g = tl.load(g_ptr)
    l1_weight = tl.load(consts_ptr + 2)
    ssim_weight = tl.load(consts_ptr + 3)
    tl.store(out_ptr + e, g * (l1_weight * sign - ssim_weight * (sa + 2.0 * x * sb + y * sk)), mask=live)
