"""The Triton GPU backend ("triton", issue 27): whole-view tile rasterisers for CUDA tensors.

    runs(device, dtype) -> bool, why_not() -> str | None       the seam's Backend hooks
    gaussian_view(prims, frame, colors, t_min)                    op "view.gaussian" (kinds/gaussian.py)
    neural_view(prims, frame, colors, t_min)                      op "view.neural" (kinds/neural.py)
        -> (Σ w c (H, W, 3), Σ w z (H, W), T (H, W), counters (4,), the visible count (0-dim))
    sh_color(sh, v, degree) -> colour (P, 3)                      op "sh_color" (core/render/rasterize.py)
    neural_accumulate(...), gaussian_accumulate(...)              the statistics ops (core/train/strategy.py)
    bin_tiles(bounds, visible, order, height, width) -> (offsets, entries)   the per-tile depth-ordered lists

Why Triton: its JIT compiles the kernels on a user's first GPU run with no nvcc and nothing to
download (the wheel ships its compiler), and `TRITON_INTERPRET=1` runs the very same kernels on
CPU tensors, so CI (no GPU) tests them against the torch twins on tiny views (tests/test_triton.py).

The design is gsplat's/3DGS's. Per view:
1. the kind's per-view preparation, one lane per primitive, forward and hand-written backward
   (prepare_kernels.py; the twins: `twin_view` of kinds/gaussian.py and kinds/neural.py, and
   core/render/sh.py): the colours from the SH; for Gaussians the EWA projection (mean2d, the conic
   with the 0.3 px² blur) and the 3σ boxes in one launch; for neural primitives the dual-conic
   boxes, then the ellipsoid frame M R_cam, o′, ω0 W1 R_cam, the phases c_k and 1/max s ((W2, b2)
   stay torch: an edited model's rest metric scales them);
2. in torch: the depth order (a stable sort, as the twin) and the tile binning: every visible
   primitive × the 16×16 tiles its box touches, keys (tile, depth rank) sorted by torch.sort,
   per-tile [start, end) ranges of primitive indices. The host reads the device once a view, for
   the number of those pairs (the size of the key array, as 3DGS and gsplat read it): every
   primitive keeps its place in the order, the invisible ones after the visible, so that nothing
   else waits for a count;
3. two Triton launches (gaussian_kernels.py, neural_kernels.py; the tile walk they share in
   tiles.py): the forward, one program per tile compositing front to back with early termination,
   and the backward, walking each pixel's list back to front from its final T with atomic adds of
   the per-primitive gradients. The kernels read the primitives through the lists: nothing is
   gathered into depth order, nothing is stored per pair, and the launches per view do not depend
   on the primitive count.
The population-control statistics come out of autograd as on every path: the means' gradient
(Gaussians) and the MLP's gradients (neural) are what the strategies read (core/train/strategy.py).

Where it runs: CUDA tensors (float32, float64) when triton is installed and a GPU is present; CPU
tensors only with the interpreter on (TRITON_INTERPRET=1 before triton is imported) AND the backend
chosen explicitly with `backends.using("triton")`, so that the CPU path never changes by itself.
Triton is imported at the first view drawn here, never at start-up.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import os

import torch

from radfield.errors import RadfieldError
from radfield.util.transfer import to_device

NAME = "triton"
TILE = 16   # tile side in pixels (gaussian_kernels.SIDE)
# The kernels' compile options. No FMA contraction (as the fused CPU build, -ffp-contract=off): the
# backward recomputes each pair's α exactly as the forward did, whatever instructions the compiler
# picks in either kernel. 8 warps: one thread per pixel of a 16×16 tile, as 3DGS's rasteriser; with
# 4 (two pixels a thread) the windowed neural backward needs more than 255 registers and spills
# 760 bytes a thread, the other neural kernels 192–255 registers; with 8 none spills (ptxas for
# sm_90: 32 registers for the Gaussian kernels, 121/153 for the neural forward, 188/233 for its
# backward, hard-edged/windowed; tests/test_triton.py checks that none spills).
COMPILE_OPTIONS = {"enable_fp_fusion": False, "num_warps": 8}
# the per-primitive kernels (prepare_kernels.py): 4 warps for their 128 primitives a program; no FMA
# contraction either, so that the backward's recomputed sums take the forward's clamp
PREPARE_OPTIONS = {"enable_fp_fusion": False, "num_warps": 4}


@contextlib.contextmanager
def _launching():
    """A kernel that fails to compile or launch on this GPU (an old Triton, too few registers, a
    driver the wheel's compiler does not know): one error line with the way out, not a traceback
    from inside Triton. The interpreter's errors (the tests') pass through as they are."""
    try:
        yield
    except Exception as error:
        if interpreting():
            raise
        first = (str(error).strip().splitlines() or [""])[0][:200]
        raise RadfieldError(f"the Triton GPU kernels failed on this machine ({type(error).__name__}: {first}); "
                            "RADFIELD_KERNELS=torch runs the readable torch kernels instead") from None


@functools.cache
def _installed() -> bool:
    return importlib.util.find_spec("triton") is not None


def interpreting() -> bool:
    """TRITON_INTERPRET=1: triton runs its kernels on CPU tensors (numpy), slowly: the tests' mode."""
    return os.environ.get("TRITON_INTERPRET", "").strip() in ("1", "true", "True")


def _chosen() -> bool:
    from radfield.core import backends

    return backends.chosen() == NAME


def runs(device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> bool:
    """Whether the backend runs tensors of (device, dtype) here (cheap: triton is not imported)."""
    if dtype is not None and dtype not in (torch.float32, torch.float64):
        return False
    if not _installed():
        return False
    kind = None if device is None else torch.device(device).type
    on_cpu = interpreting() and _chosen()
    if kind == "cuda":
        return torch.cuda.is_available()
    if kind == "cpu":
        return on_cpu
    return kind is None and (on_cpu or torch.cuda.is_available())


def why_not() -> str | None:
    """Why the backend cannot run at all here, or None."""
    if not _installed():
        return "triton is not installed"
    if not torch.cuda.is_available() and not interpreting():
        return "no CUDA GPU (and TRITON_INTERPRET is not set)"
    return None


# --- tile binning (torch) ------------------------------------------------------------------------

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


# --- the views: one autograd op per kind, two launches each ------------------------------------------

def _sizes(height: int, width: int) -> tuple[int, int]:
    return -(-width // TILE), -(-width // TILE) * -(-height // TILE)


def _outputs(like: torch.Tensor, height: int, width: int, tiles: int):
    """Σ w c, Σ w z, T, last (the list position after each pixel's last composited pair) and the
    per-tile counts (evaluated, composited, terminated)."""
    return (like.new_zeros(height, width, 3), like.new_zeros(height, width), like.new_ones(height, width),
            torch.zeros(height, width, dtype=torch.int32, device=like.device),
            torch.zeros(tiles, 3, dtype=torch.int32, device=like.device))


def _counters(counts: torch.Tensor, bounds: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """(evaluated, composited, terminated, candidate pairs): the candidates are the visible boxes' pixels."""
    x0, y0, x1, y1 = bounds.long().unbind(-1)
    return torch.cat([counts.long().sum(0), torch.where(visible, (x1 - x0 + 1) * (y1 - y0 + 1), 0).sum().reshape(1)])


def _upstream(like: torch.Tensor, height: int, width: int, g_color, g_depth, g_trans):
    return [like.new_zeros(shape) if g is None else g.contiguous()
            for g, shape in ((g_color, (height, width, 3)), (g_depth, (height, width)), (g_trans, (height, width)))]


def _prepared(tensors, bounds: torch.Tensor, visible: torch.Tensor, order: torch.Tensor, height: int, width: int,
              t_min: float):
    """What both views' forwards set up before their launch: the per-primitive inputs contiguous,
    int32 bounds, the tile lists, the constants, the tile grid and the zeroed outputs."""
    inputs = [t.contiguous() for t in tensors]
    bounds = bounds.to(torch.int32).contiguous()
    offsets, entries = bin_tiles(bounds, visible, order, height, width)
    tiles_x, tiles = _sizes(height, width)
    return (inputs, bounds, offsets, entries, _constants(inputs[0], t_min), tiles_x, tiles,
            _outputs(inputs[0], height, width, tiles))


def _constants(like: torch.Tensor, t_min: float) -> torch.Tensor:
    """(t_min, α_min, α_max, 1) in the inputs' dtype (the kernels' thresholds are the twin's)."""
    return _constants_on(t_min, like.dtype, like.device)


@functools.lru_cache(maxsize=16)
def _constants_on(t_min: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """Made once per (t_min, dtype, device), not every view."""
    from radfield.core.render.kernels import ALPHA_MAX, ALPHA_MIN

    return to_device(torch.tensor([t_min, ALPHA_MIN, ALPHA_MAX, 1.0], dtype=dtype), device)


class _GaussianView(torch.autograd.Function):
    """(Σ w c, Σ w z, T, counters) of splats composited in the depth order `order`, differentiable
    w.r.t. mean2d, conic, opacity, colors and depth (all (P, ...), the kernels read them through
    the tile lists: nothing is gathered into that order)."""

    @staticmethod
    def forward(ctx, bounds, visible, order, height, width, t_min, mean2d, conic, opacity, colors, depth):
        from radfield.core.backends.gpu import gaussian_kernels as K

        inputs, bounds, offsets, entries, consts, tiles_x, tiles, outputs = _prepared(
            (mean2d, conic, opacity, colors, depth), bounds, visible, order, height, width, t_min)
        acc_color, acc_depth, trans, last, counts = outputs
        with _launching():
            K.gaussian_forward[(tiles,)](offsets, entries, bounds, *inputs, consts, acc_color, acc_depth, trans, last,
                                         counts, height, width, tiles_x, SIDE=TILE, **COMPILE_OPTIONS)
        ctx.sizes = (height, width, tiles_x, tiles)
        ctx.save_for_backward(offsets, entries, bounds, *inputs, consts, trans, last)
        counters = _counters(counts, bounds, visible)
        ctx.mark_non_differentiable(counters)
        return acc_color, acc_depth, trans, counters

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_color, g_depth, g_trans, _):
        from radfield.core.backends.gpu import gaussian_kernels as K

        offsets, entries, bounds, *inputs, consts, trans, last = ctx.saved_tensors
        height, width, tiles_x, tiles = ctx.sizes
        upstream = _upstream(inputs[0], height, width, g_color, g_depth, g_trans)
        grads = [torch.zeros_like(t) for t in inputs]   # mean2d, conic, opacity, colors, depth
        with _launching():
            K.gaussian_backward[(tiles,)](offsets, entries, bounds, *inputs, consts, trans, last, *upstream, *grads,
                                          height, width, tiles_x, SIDE=TILE, **COMPILE_OPTIONS)
        return None, None, None, None, None, None, *grads


class _NeuralView(torch.autograd.Function):
    """As _GaussianView for neural primitives: differentiable w.r.t. m_cam, o_ell, w_cam, c, w2, b2,
    inv_smax, colors and depth (all (P, ...)); `window`: the windowed density."""

    @staticmethod
    def forward(ctx, bounds, visible, order, intrinsics, height, width, t_min, window, m_cam, o_ell, w_cam, c, w2, b2,
                inv_smax, colors, depth):
        from radfield.core.backends.gpu import neural_kernels as K

        inputs, bounds, offsets, entries, consts, tiles_x, tiles, outputs = _prepared(
            (m_cam, o_ell, w_cam, c, w2, b2, inv_smax, colors, depth), bounds, visible, order, height, width, t_min)
        intrinsics = intrinsics.detach().contiguous()
        units = c.shape[1]
        acc_color, acc_depth, trans, last, counts = outputs
        with _launching():
            K.neural_forward[(tiles,)](offsets, entries, bounds, intrinsics, *inputs, consts, acc_color, acc_depth, trans,
                                       last, counts, height, width, tiles_x, units, SIDE=TILE, NP=_padded(units),
                                       WINDOW=bool(window), **COMPILE_OPTIONS)
        ctx.sizes = (height, width, tiles_x, tiles, units, bool(window))
        ctx.save_for_backward(offsets, entries, bounds, intrinsics, *inputs, consts, trans, last)
        counters = _counters(counts, bounds, visible)
        ctx.mark_non_differentiable(counters)
        return acc_color, acc_depth, trans, counters

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_color, g_depth, g_trans, _):
        from radfield.core.backends.gpu import neural_kernels as K

        offsets, entries, bounds, intrinsics, *inputs, consts, trans, last = ctx.saved_tensors
        height, width, tiles_x, tiles, units, window = ctx.sizes
        upstream = _upstream(inputs[0], height, width, g_color, g_depth, g_trans)
        grads = [torch.zeros_like(t) for t in inputs]   # m_cam, o_ell, w_cam, c, w2, b2, inv_smax, colors, depth
        with _launching():
            K.neural_backward[(tiles,)](offsets, entries, bounds, intrinsics, *inputs, consts, trans, last, *upstream,
                                        *grads, height, width, tiles_x, units, SIDE=TILE, NP=_padded(units),
                                        WINDOW=window, **COMPILE_OPTIONS)
        return None, None, None, None, None, None, None, None, *grads


class _SHColor(torch.autograd.Function):
    """max(Σ_k Y_k(v/|v|) sh_k + 0.5, 0) (prepare_kernels.py), differentiable w.r.t. sh and v."""

    @staticmethod
    def forward(ctx, sh, v, degree):
        from radfield.core.backends.gpu import prepare_kernels as K

        sh, v = sh.contiguous(), v.contiguous()
        out = v.new_empty(v.shape[0], 3)
        count = v.shape[0]
        with _launching():
            K.sh_color_forward[(-(-count // K.BLOCK),)](sh, v, out, count, sh.shape[1], COEFFS=(degree + 1) ** 2,
                                                        BLOCK=K.BLOCK, **PREPARE_OPTIONS)
        ctx.degree = degree
        ctx.save_for_backward(sh, v)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        from radfield.core.backends.gpu import prepare_kernels as K

        sh, v = ctx.saved_tensors
        g_sh, g_v = torch.zeros_like(sh), torch.empty_like(v)
        count = v.shape[0]
        with _launching():
            K.sh_color_backward[(-(-count // K.BLOCK),)](grad.contiguous(), sh, v, g_sh, g_v, count, sh.shape[1],
                                                         COEFFS=(ctx.degree + 1) ** 2, BLOCK=K.BLOCK, **PREPARE_OPTIONS)
        return g_sh, g_v, None


class _NeuralPrep(torch.autograd.Function):
    """The neural primitives' per-view tensors (m_cam (P, 3, 3), o_ell (P, 3), w_cam (P, N, 3), c (P, N),
    inv_smax (P,); prepare_kernels.py), differentiable w.r.t. means, log_scales, quats, w1 and b1;
    `view` = (o, R_cam row-major, ω0) in their dtype."""

    @staticmethod
    def forward(ctx, means, log_scales, quats, w1, b1, view):
        from radfield.core.backends.gpu import prepare_kernels as K

        inputs = [t.contiguous() for t in (means, log_scales, quats, w1, b1, view)]
        count, units = b1.shape
        outputs = (means.new_empty(count, 3, 3), means.new_empty(count, 3), w1.new_empty(count, units, 3),
                   b1.new_empty(count, units), means.new_empty(count))
        with _launching():
            K.neural_prep_forward[(-(-count // K.BLOCK),)](*inputs, *outputs, count, units, NP=_padded(units),
                                                           BLOCK=K.BLOCK, **PREPARE_OPTIONS)
        ctx.save_for_backward(*inputs[:4], inputs[5])
        return outputs

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads):
        from radfield.core.backends.gpu import prepare_kernels as K

        means, log_scales, quats, w1, view = ctx.saved_tensors
        count, units = w1.shape[:2]
        shapes = ((count, 3, 3), (count, 3), (count, units, 3), (count, units), (count,))
        grads = [means.new_zeros(shape) if g is None else g.contiguous() for g, shape in zip(grads, shapes)]
        out = [torch.empty_like(t) for t in (means, log_scales, quats, w1)] + [w1.new_empty(count, units)]
        with _launching():
            K.neural_prep_backward[(-(-count // K.BLOCK),)](*grads, means, log_scales, quats, w1, view, *out, count,
                                                            units, NP=_padded(units), BLOCK=K.BLOCK,
                                                            **PREPARE_OPTIONS)
        return (*out, None)


def neural_prep(prims, campos: torch.Tensor, cam_rot: torch.Tensor) -> tuple:
    """(m_cam, o_ell, w_cam, c, inv_smax) of kinds/neural.py view_tensors (without its (W2, b2)) on
    Triton: one launch, and one for the backward."""
    view = torch.cat([campos, cam_rot.reshape(9), campos.new_full((1,), float(prims.omega0))])
    return _NeuralPrep.apply(prims.means, prims.log_scales, prims.quats, prims.w1, prims.b1, view)


class _GaussianPrep(torch.autograd.Function):
    """The splats' EWA projection (mean2d (P, 2), conic (P, 3), the covariance's (a, b, c) (P, 3);
    prepare_kernels.py), differentiable w.r.t. means_cam, log_scales and quats, and their pixel
    boxes (P, 4) int32 and visibility (P,) bool; `view` = (W (9), fx, fy, cx, cy, near, the Jacobian
    point's clamp (4)) in their dtype."""

    @staticmethod
    def forward(ctx, means_cam, log_scales, quats, view, width, height):
        from radfield.core.backends.gpu import prepare_kernels as K

        inputs = [t.contiguous() for t in (means_cam, log_scales, quats, view)]
        count, device = means_cam.shape[0], means_cam.device
        outputs = (means_cam.new_empty(count, 2), means_cam.new_empty(count, 3), means_cam.new_empty(count, 3),
                   torch.empty(count, 4, dtype=torch.int32, device=device), torch.empty(count, dtype=torch.int8, device=device))
        with _launching():
            K.gaussian_prep_forward[(-(-count // K.BLOCK),)](*inputs, *outputs, count, width, height, BLOCK=K.BLOCK,
                                                             **PREPARE_OPTIONS)
        ctx.save_for_backward(*inputs)
        bounds, visible = outputs[3], outputs[4].bool()
        ctx.mark_non_differentiable(bounds, visible)
        return (*outputs[:3], bounds, visible)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_mean2d, g_conic, g_cov, _bounds, _visible):
        from radfield.core.backends.gpu import prepare_kernels as K

        means_cam, log_scales, quats, view = ctx.saved_tensors
        count = means_cam.shape[0]
        grads = [means_cam.new_zeros(count, width) if g is None else g.contiguous()
                 for g, width in ((g_mean2d, 2), (g_conic, 3), (g_cov, 3))]
        out = [torch.empty_like(t) for t in (means_cam, log_scales, quats)]
        with _launching():
            K.gaussian_prep_backward[(-(-count // K.BLOCK),)](*grads, means_cam, log_scales, quats, view, *out, count,
                                                              BLOCK=K.BLOCK, **PREPARE_OPTIONS)
        return (*out, None, None, None)


def gaussian_prep(prims, frame) -> tuple:
    """(bounds, visible, (mean2d, conic, opacity)) of kinds/gaussian.py twin_view (ewa_view and
    splat_bounds) on Triton: one launch, and one for the backward. The clamp of the Jacobian's point
    is the twin's, from the camera's numbers."""
    camera = frame.camera
    margin_x, margin_y = 0.15 * camera.width / camera.fx, 0.15 * camera.height / camera.fy
    numbers = torch.tensor([camera.fx, camera.fy, camera.cx, camera.cy, frame.near,
                            -camera.cx / camera.fx - margin_x, (camera.width - camera.cx) / camera.fx + margin_x,
                            -camera.cy / camera.fy - margin_y, (camera.height - camera.cy) / camera.fy + margin_y],
                           dtype=frame.means_cam.dtype)
    view = torch.cat([frame.w2c[:3, :3].reshape(9), to_device(numbers, frame.means_cam.device)])
    mean2d, conic, _, bounds, visible = _GaussianPrep.apply(frame.means_cam, prims.log_scales, prims.quats, view,
                                                            camera.width, camera.height)
    return bounds, visible, (mean2d, conic, torch.sigmoid(prims.opacities))


@torch.no_grad()
def neural_bounds(prims, frame) -> tuple[torch.Tensor, torch.Tensor]:
    """(bounds (P, 4) int32, visible (P,) bool) of kinds/base.py ellipsoid_bounds in one launch."""
    from radfield.core.backends.gpu import prepare_kernels as K

    means_cam = frame.means_cam.detach().contiguous()
    count, camera = means_cam.shape[0], frame.camera
    view = torch.cat([frame.w2c[:3, :3].reshape(9), frame.intrinsics]).detach()
    bounds = torch.empty(count, 4, dtype=torch.int32, device=means_cam.device)
    visible = torch.empty(count, dtype=torch.int8, device=means_cam.device)
    with _launching():
        K.neural_bounds[(-(-count // K.BLOCK),)](means_cam, prims.log_scales.detach().contiguous(),
                                                 prims.quats.detach().contiguous(), view, bounds, visible, count,
                                                 camera.width, camera.height, BLOCK=K.BLOCK, **PREPARE_OPTIONS)
    return bounds, visible.bool()


def sh_color(sh: torch.Tensor, v: torch.Tensor, degree: int) -> torch.Tensor:
    """Op "sh_color" on Triton: sh.sh_to_color(sh, normalize(v), degree) (v = μ − o) in one launch, and
    one for its backward."""
    if v.shape[0] == 0:   # no grid to launch: the twin's empty result
        from radfield.core.render.sh import sh_to_color

        return sh_to_color(sh, torch.nn.functional.normalize(v, dim=-1), degree)
    return _SHColor.apply(sh, v, degree)


# --- population control's statistics of a view (statistics_kernels.py; the fused CPU ops' signatures) ------

def neural_accumulate(grad_acc, count_acc, means, log_scales, g_w1, g_b1, g_w2, g_b2, w2c, normals,
                      radius_scale: float, near: float) -> None:
    """Op "neural_accumulate" on Triton: one view's visibility and MLP-gradient signal added into
    the accumulators in place (twin: core/train/strategy.py `_Strategy.accumulate`)."""
    _accumulate(grad_acc, count_acc, means, log_scales, None, (g_w1, g_b1, g_w2, g_b2), w2c, normals,
                (radius_scale, near, 1.0, 1.0, 0.0, 0.0))


def gaussian_accumulate(grad_acc, count_acc, means, log_scales, grad_means, w2c, normals, radius_scale: float,
                        near: float, fx: float, fy: float, width: float, height: float) -> None:
    """Op "gaussian_accumulate" on Triton: one view's visibility and screen-space gradient signal
    added into the accumulators in place."""
    _accumulate(grad_acc, count_acc, means, log_scales, grad_means, None, w2c, normals,
                (radius_scale, near, fx, fy, width / 2, height / 2))


@torch.no_grad()
def _accumulate(grad_acc, count_acc, means, log_scales, grad_means, mlp_grads, w2c, normals, numbers) -> None:
    from radfield.core.backends.gpu import statistics_kernels as K

    count = means.shape[0]
    if count == 0:
        return
    frame = torch.cat([w2c.reshape(12), normals.reshape(12), to_device(torch.tensor(numbers, dtype=means.dtype),
                                                                       means.device)])
    neural = mlp_grads is not None
    g_w1, g_b1, g_w2, g_b2 = (t.contiguous() for t in mlp_grads) if neural else (means,) * 4
    units = g_b1.shape[1] if neural else 1
    with _launching():
        K.accumulate[(-(-count // K.BLOCK),)](grad_acc, count_acc, means.detach().contiguous(),
                                              log_scales.detach().contiguous(),
                                              means if neural else grad_means.contiguous(), g_w1, g_b1, g_w2, g_b2,
                                              frame, count, units, NP=_padded(units), NEURAL=neural, BLOCK=K.BLOCK,
                                              **PREPARE_OPTIONS)


def _padded(units: int) -> int:
    """The hidden units' axis in the kernels: a power of two (the padding is masked)."""
    return max(1 << (units - 1).bit_length(), 1)


def _front_to_back(frame, visible: torch.Tensor) -> torch.Tensor:
    """Every primitive's index: the visible ones by camera-space depth, stable, as the twin orders
    them, then the others (a sort of all of them: picking the visible ones out would read their count)."""
    return torch.argsort(torch.where(visible, frame.depth.detach(), torch.inf), stable=True)


def gaussian_view(prims, frame, colors: torch.Tensor, t_min: float):
    """Op "view.gaussian" on Triton: the twin's per-view preparation (kinds/gaussian.py: twin_view,
    the EWA projection and the bounds) by the preparation kernel (gaussian_prep) and depth order,
    then the tile kernels; returns (Σ w c, Σ w z, T, counters (evaluated,
    composited, terminated, candidate pairs), the number of visible primitives (0-dim))."""
    from radfield.core import kinds

    # the twin's EWA projection and bounds in one launch (gaussian_prep)
    if len(prims.means):
        bounds, visible, (mean2d, conic, opacity) = gaussian_prep(prims, frame)
    else:   # nothing to launch
        bounds, visible, (mean2d, conic, opacity) = kinds.of(prims).twin_view(prims, frame)
    camera = frame.camera
    out = _GaussianView.apply(bounds, visible, _front_to_back(frame, visible), camera.height, camera.width,
                              float(t_min), mean2d, conic, opacity, colors, frame.depth)
    return (*out, visible.sum())


def neural_view(prims, frame, colors: torch.Tensor, t_min: float):
    """Op "view.neural" on Triton: the twin's bounds and per-view tensors (kinds/neural.py:
    twin_view: the ellipsoid frame, the MLP phases, (W2, b2)), the frame and phases by the
    preparation kernel (neural_prep), then the tile kernels; returns as gaussian_view."""
    from radfield.core.kinds.neural import density_weights

    # the twin's bounds (kinds/base.py ellipsoid_bounds) and per-view tensors (view_tensors), each in one launch
    if len(prims.means):
        bounds, visible = neural_bounds(prims, frame)
        m_cam, o_ell, w_cam, c, inv_smax = neural_prep(prims, frame.campos, frame.c2w[:3, :3])
        w2, b2 = density_weights(prims, frame.campos - prims.means)
    else:   # nothing to launch
        from radfield.core.kinds.base import ellipsoid_bounds
        from radfield.core.kinds.neural import view_tensors

        bounds, visible = ellipsoid_bounds(prims, frame)
        m_cam, o_ell, w_cam, c, w2, b2, inv_smax = view_tensors(prims, frame.campos, frame.c2w[:3, :3])
    camera = frame.camera
    out = _NeuralView.apply(bounds, visible, _front_to_back(frame, visible), frame.intrinsics, camera.height,
                            camera.width, float(t_min), prims.window, m_cam.reshape(-1, 9), o_ell, w_cam, c, w2, b2,
                            inv_smax, colors, frame.depth)
    return (*out, visible.sum())
