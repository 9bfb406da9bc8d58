"""Differentiable splatting of primitives of any kind (core/kinds/): one functional entry point.

    render(prims, camera, background=...) -> Render(color (H,W,3), alpha (H,W), depth (H,W), meta)

Pipeline:
0. the primitives as this view sees them (their kind's `at_view`: a time-conditioned kind's at
   the camera's time, core/kinds/dynamic.py; every other kind's as they are);
1. per primitive, once per view: camera-space depth, frustum culling, a tight projected bound
   (the kind's: the dual conic of the bounding ellipsoid for neural primitives, 3σ of the EWA
   covariance for Gaussians), and everything that depends only on the camera centre (o', c_k,
   SH colour);
2. primitives sorted by depth;
3. front-to-back compositing (paper eq. 4) with early termination, by one of three implementations
   with the same semantics, chosen per device, dtype and kind by the kernel-backend seam
   (radfield.core.backends: op "view.<kind>"):
   - on the CPU, the fused C++ tile rasteriser (core/backends/fused.py, core/backends/csrc/view_kernels.cpp), the
     default, with fused ops for the colour and the neural frame of step 1;
   - on CUDA, the Triton tile kernels (core/backends/gpu/), with Triton kernels for step 1;
   - the readable torch twin (core/splat/composite.py: composite_view; RADFIELD_KERNELS=torch,
     other devices): the pixels of each projected bound become flat (primitive, pixel) pairs,
     evaluated in depth-ordered chunks of at most `max_pairs` (pixels whose transmittance fell
     below `t_min` drop out of later chunks) and composited by `composite_pairs`, the one routine
     of eq. 4 that the retraining teacher (edit/retrain.py) shares.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, MutableMapping
from typing import NamedTuple

import torch

from radfield.core import backends, kinds
from radfield.core.geometry.cameras import Camera
from radfield.core.splat.view import ViewFrame
from radfield.core.splat.composite import composite_view
from radfield.core.splat.sh import sh_parts, sh_to_color
from radfield.util.transfer import to_device

T_MIN = 1e-4            # 3DGS early termination threshold on transmittance


class Render(NamedTuple):
    color: torch.Tensor  # (H, W, 3)
    alpha: torch.Tensor  # (H, W) accumulated opacity 1 − T
    depth: torch.Tensor  # (H, W) opacity-weighted mean camera-space depth of primitive centres (0 where empty)
    meta: "RenderCounts"


class RenderCounts(MutableMapping):
    """A render's counts (visible, pairs, contributing_pairs, candidate_pairs, terminated_pixels),
    read from the device at the first look: on a GPU a read waits for every queued kernel, so a
    training step that never looks never waits. Otherwise a dict."""

    KEYS = ("visible", "pairs", "contributing_pairs", "candidate_pairs", "terminated_pixels")

    def __init__(self, read: Callable[[], list[int]]):
        self._read, self._values = read, None

    def _counts(self) -> dict:
        if self._values is None:
            self._values = dict(zip(self.KEYS, self._read()))
            self._read = None
        return self._values

    def __getitem__(self, key: str) -> int:
        return self._counts()[key]

    def __setitem__(self, key: str, value) -> None:
        self._counts()[key] = value

    def __delitem__(self, key: str) -> None:
        del self._counts()[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._counts())

    def __len__(self) -> int:
        return len(self._counts())

    def __repr__(self) -> str:
        return repr(self._counts()) if self._values is not None else "RenderCounts(not read yet)"


def render(prims: kinds.Primitives, camera: Camera, *, background=(1.0, 1.0, 1.0), near: float = 0.01,
           sh_degree: int | None = None, max_pairs: int = 1 << 20, t_min: float = T_MIN) -> Render:
    """Render one view. Differentiable w.r.t. every tensor of `prims` (and `background` if a tensor).

    sh_degree: use SH bands up to this degree (default: all the model has).
    max_pairs: torch path only: pixel-primitive pairs evaluated at once (results do not depend
        on it). Under torch.no_grad() it bounds the working memory: one chunk's pair tensors at a
        time. With gradients it does NOT bound memory: autograd keeps every chunk's saved tensors
        until backward, so a differentiable torch-path render holds memory proportional to all the
        view's candidate pairs (`meta["candidate_pairs"]`), whatever max_pairs is: measured with
        float32 primitives (scripts/saved_memory.py torch, 3000 primitives, one 128×128 view)
        ≈ 420 bytes per pair for neural primitives and ≈ 120 for Gaussians, the same for
        max_pairs = 2^10 … 2^20. The fused CPU path keeps nothing per pair: its memory is
        O(pixels + per-tile primitive lists + per-primitive tensors), with or without gradients.
    """
    # a time-conditioned kind's primitives at the camera's time (kinds/base.py: at_view); others as they are
    prims = kinds.of(prims).at_view(prims, camera)
    device, dtype = prims.means.device, prims.means.dtype
    height, width = camera.height, camera.width
    # the camera's numbers made on the host, sent in one copy that does not wait for the device
    c2w = camera.c2w.to(dtype)
    on_host = torch.cat([c2w.reshape(16), torch.linalg.inv(c2w).reshape(16),
                         torch.tensor([camera.fx, camera.fy, camera.cx, camera.cy, near], dtype=dtype)])
    c2w, w2c, intrinsics = to_device(on_host, device).split((16, 16, 5))
    c2w, w2c = c2w.view(4, 4), w2c.view(4, 4)
    campos = c2w[:3, 3]
    means_cam = prims.means @ w2c[:3, :3].T + w2c[:3, 3]
    depth = means_cam[:, 2]
    degree = prims.sh_degree if sh_degree is None else min(sh_degree, prims.sh_degree)
    kind = kinds.of(prims)
    parts = sh_parts(prims.sh)   # the trainer's (sh_dc, sh_rest), read in place by a backend's colour op
    color_parts = backends.kernel(backends.Op.SH_COLOR_PARTS, device, dtype) if parts is not None else None
    color_op = backends.kernel(backends.Op.SH_COLOR, device, dtype)
    if color_parts is not None:
        colors = color_parts(*parts, prims.means, campos, degree)
    elif color_op is not None:   # (fused: core/backends/csrc/prepare_kernels.cpp)
        colors = color_op(prims.sh, prims.means - campos, degree)
    else:
        colors = sh_to_color(prims.sh, torch.nn.functional.normalize(prims.means - campos, dim=-1), degree)

    frame = ViewFrame(camera, c2w, w2c, campos, means_cam, depth, intrinsics, near)
    view_op = backends.kernel(backends.view_op(kind.name), device, dtype)
    if view_op is not None:
        # the whole view in one backend call (fused: core/backends/csrc/view_kernels.cpp; Triton:
        # core/backends/gpu/): the kind's bounds, depth order and per-view tensors, then the same
        # compositing rules; it reads the per-primitive tensors itself (the fused kernels gather and
        # scatter them, the Triton ones read them through the tile lists), so no autograd op of a
        # gather is recorded here
        acc_color, acc_depth, transmittance, counters, visible = view_op(prims, frame, colors, t_min)

        def counts():   # read only when someone looks (RenderCounts); a backend may make them only then
            evaluated, composited, terminated, candidates = (counters() if callable(counters) else counters).tolist()
            return [int(visible), evaluated, composited, candidates, terminated]
    else:
        bounds, visible, view = kind.twin_view(prims, frame)
        ids = torch.nonzero(visible).squeeze(1)
        ids = ids[torch.argsort(depth[ids].detach(), stable=True)]   # front to back; position = depth rank
        bounds = bounds[ids]
        acc_color, acc_depth, transmittance, (n_pairs, n_contrib, n_done) = composite_view(
            kind.pair_kernel(prims), [t[ids] for t in view], bounds, colors[ids], depth[ids], intrinsics, height, width,
            max_pairs, t_min)
        x0, y0, x1, y1 = bounds.unbind(-1)
        n_candidates = int(((x1 - x0 + 1) * (y1 - y0 + 1)).sum())
        counts = lambda: [ids.numel(), n_pairs, n_contrib, n_candidates, n_done]

    bg = to_device(background if isinstance(background, torch.Tensor) else torch.tensor(background, dtype=dtype),
                   device, dtype)
    color = acc_color + transmittance[..., None] * bg
    alpha = 1.0 - transmittance
    mean_depth = acc_depth / torch.clamp_min(alpha, 1e-10)
    return Render(color, alpha, mean_depth, RenderCounts(counts))
