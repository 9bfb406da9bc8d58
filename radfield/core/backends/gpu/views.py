"""Ops "view.gaussian" and "view.neural" on the Triton backend: one autograd op per kind around the
tile kernels (gaussian_kernels.py, neural_kernels.py), after the kind's preparation
(preparation.py), the depth order and the binning (binning.py). Returns of both views:
(Σ w c (H, W, 3), Σ w z (H, W), T (H, W), a function that makes the counters (evaluated,
composited, terminated, candidate pairs) when someone reads them, the number of visible
primitives (0-dim))."""

from __future__ import annotations

import functools

import torch

from radfield.core.backends.gpu.binning import bin_tiles
from radfield.core.backends.gpu.launch import COMPILE_OPTIONS, NEURAL_BACKWARD_OPTIONS, TILE, launching
from radfield.core.backends.gpu.preparation import gaussian_prep, neural_bounds, neural_prep
from radfield.util.transfer import device_constants


def _sizes(height: int, width: int) -> tuple[int, int]:
    return -(-width // TILE), -(-width // TILE) * -(-height // TILE)


def _outputs(like: torch.Tensor, height: int, width: int, tiles: int):
    """Σ w c, Σ w z, T, last (the list position after each pixel's last composited pair) and the
    per-tile counts (evaluated, composited, terminated): allocated, not filled, since the forward
    writes every pixel of every tile (tiles.py: _store_tile), an empty list's too."""
    return (like.new_empty(height, width, 3), like.new_empty(height, width), like.new_empty(height, width),
            torch.empty(height, width, dtype=torch.int32, device=like.device),
            torch.empty(tiles, 3, dtype=torch.int32, device=like.device))


def _zero_grads(inputs: list[torch.Tensor]) -> list[torch.Tensor]:
    """Zeroed gradients shaped as the inputs (one dtype), for the backward's atomic adds: views of
    one buffer, so one fill launches where one a tensor would."""
    sizes = [t.numel() for t in inputs]
    flat = inputs[0].new_zeros(sum(sizes))
    return [chunk.view(t.shape) for chunk, t in zip(flat.split(sizes), inputs)]


def _counters(counts: torch.Tensor, bounds: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """(evaluated, composited, terminated, candidate pairs) from the tiles' counts: the candidates are
    the visible boxes' pixels. Made only when someone reads a render's counts (rasterize.RenderCounts)."""
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
    from radfield.core.splat.kernels import ALPHA_MAX, ALPHA_MIN

    return device_constants((float(t_min), ALPHA_MIN, ALPHA_MAX, 1.0), like.dtype, like.device)


class _GaussianView(torch.autograd.Function):
    """(Σ w c, Σ w z, T, the tiles' counts (tiles, 3)) of splats composited in the depth order `order`, differentiable
    w.r.t. mean2d, conic, opacity, colors and depth (all (P, ...), the kernels read them through
    the tile lists: nothing is gathered into that order)."""

    @staticmethod
    def forward(ctx, bounds, visible, order, height, width, t_min, mean2d, conic, opacity, colors, depth):
        from radfield.core.backends.gpu import gaussian_kernels as K

        inputs, bounds, offsets, entries, consts, tiles_x, tiles, outputs = _prepared(
            (mean2d, conic, opacity, colors, depth), bounds, visible, order, height, width, t_min)
        acc_color, acc_depth, trans, last, counts = outputs
        with launching():
            K.gaussian_forward[(tiles,)](offsets, entries, bounds, *inputs, consts, acc_color, acc_depth, trans, last,
                                         counts, height, width, tiles_x, SIDE=TILE, **COMPILE_OPTIONS)
        ctx.sizes = (height, width, tiles_x, tiles)
        ctx.save_for_backward(offsets, entries, bounds, *inputs, consts, trans, last)
        ctx.mark_non_differentiable(counts)
        return acc_color, acc_depth, trans, counts

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_color, g_depth, g_trans, _):
        from radfield.core.backends.gpu import gaussian_kernels as K

        offsets, entries, bounds, *inputs, consts, trans, last = ctx.saved_tensors
        height, width, tiles_x, tiles = ctx.sizes
        upstream = _upstream(inputs[0], height, width, g_color, g_depth, g_trans)
        grads = _zero_grads(inputs)   # mean2d, conic, opacity, colors, depth
        with launching():
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
        with launching():
            K.neural_forward[(tiles,)](offsets, entries, bounds, intrinsics, *inputs, consts, acc_color, acc_depth, trans,
                                       last, counts, height, width, tiles_x, SIDE=TILE, UNITS=units,
                                       WINDOW=bool(window), **COMPILE_OPTIONS)
        ctx.sizes = (height, width, tiles_x, tiles, units, bool(window))
        ctx.save_for_backward(offsets, entries, bounds, intrinsics, *inputs, consts, trans, last)
        ctx.mark_non_differentiable(counts)
        return acc_color, acc_depth, trans, counts

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_color, g_depth, g_trans, _):
        from radfield.core.backends.gpu import neural_kernels as K

        offsets, entries, bounds, intrinsics, *inputs, consts, trans, last = ctx.saved_tensors
        height, width, tiles_x, tiles, units, window = ctx.sizes
        upstream = _upstream(inputs[0], height, width, g_color, g_depth, g_trans)
        grads = _zero_grads(inputs)   # m_cam, o_ell, w_cam, c, w2, b2, inv_smax, colors, depth
        with launching():
            K.neural_backward[(tiles,)](offsets, entries, bounds, intrinsics, *inputs, consts, trans, last, *upstream,
                                        *grads, height, width, tiles_x, SIDE=TILE, UNITS=units, WINDOW=window,
                                        **NEURAL_BACKWARD_OPTIONS[window])
        return None, None, None, None, None, None, None, None, *grads


def _front_to_back(frame, visible: torch.Tensor) -> torch.Tensor:
    """Every primitive's index: the visible ones by camera-space depth, stable, as the twin orders
    them, then the others (a sort of all of them: picking the visible ones out would read their count)."""
    return torch.argsort(torch.where(visible, frame.depth.detach(), torch.inf), stable=True)


def gaussian_view(prims, frame, colors: torch.Tensor, t_min: float):
    """Op "view.gaussian" on Triton: the twin's per-view preparation (core/splat/gaussian.py: the EWA
    projection and the bounds) by the preparation kernel (gaussian_prep) and depth order, then the
    tile kernels; returns (Σ w c, Σ w z, T, counters (evaluated, composited, terminated, candidate
    pairs), the number of visible primitives (0-dim))."""
    # the twin's EWA projection and bounds in one launch (gaussian_prep)
    if len(prims.means):
        bounds, visible, (mean2d, conic, opacity) = gaussian_prep(prims, frame)
    else:   # nothing to launch: the twin's (empty) tensors
        from radfield.core.splat.gaussian import ewa_view, splat_bounds

        (mean2d, conic, opacity), cov = ewa_view(prims, frame.camera, frame.w2c, frame.means_cam, frame.near)
        bounds, visible = splat_bounds(mean2d, *cov, frame.depth, frame.camera, frame.near)
    camera = frame.camera
    *sums, counts = _GaussianView.apply(bounds, visible, _front_to_back(frame, visible), camera.height, camera.width,
                                        float(t_min), mean2d, conic, opacity, colors, frame.depth)
    return (*sums, functools.partial(_counters, counts, bounds, visible), visible.sum())


def neural_view(prims, frame, colors: torch.Tensor, t_min: float):
    """Op "view.neural" on Triton: the twin's bounds and per-view tensors (splat/neural.py:
    view_tensors: the ellipsoid frame, the MLP phases, (W2, b2)), the frame and phases by the
    preparation kernel (neural_prep), then the tile kernels; returns as gaussian_view."""
    from radfield.core.splat.neural import density_weights

    # the twin's bounds (splat/view.py ellipsoid_bounds) and per-view tensors (view_tensors), each in one launch
    if len(prims.means):
        bounds, visible = neural_bounds(prims, frame)
        m_cam, o_ell, w_cam, c, inv_smax = neural_prep(prims, frame.campos, frame.c2w[:3, :3])
        w2, b2 = density_weights(prims, frame.campos - prims.means)
    else:   # nothing to launch
        from radfield.core.splat.view import ellipsoid_bounds
        from radfield.core.splat.neural import view_tensors

        bounds, visible = ellipsoid_bounds(prims, frame)
        m_cam, o_ell, w_cam, c, w2, b2, inv_smax = view_tensors(prims, frame.campos, frame.c2w[:3, :3])
    camera = frame.camera
    *sums, counts = _NeuralView.apply(bounds, visible, _front_to_back(frame, visible), frame.intrinsics,
                                      camera.height, camera.width, float(t_min), prims.window, m_cam.reshape(-1, 9),
                                      o_ell, w_cam, c, w2, b2, inv_smax, colors, frame.depth)
    return (*sums, functools.partial(_counters, counts, bounds, visible), visible.sum())
