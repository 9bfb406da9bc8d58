"""The Triton GPU backend ("triton", issue 27): whole-view tile rasterisers for CUDA tensors.

    runs(device, dtype) -> bool, why_not() -> str | None        the seam's Backend hooks (here)
    gaussian_view, neural_view (views.py)                         ops "view.gaussian", "view.neural"
        (prims, frame, colors, t_min) -> (Σ w c (H, W, 3), Σ w z (H, W), T (H, W), a function making
        the counters (4,), the visible count (0-dim))
    sh_color(sh, v, degree) (preparation.py)                      op "sh_color" (core/render/rasterize.py)
    photometric(x, y, taps, λ, C1, C2) (loss.py)                   op "photometric" (core/train/losses.py)
    project_nonnegative_(w2, b2, mask) (positivity.py)           op "project_nonnegative_" (core/train/positivity.py)
    neural_accumulate, gaussian_accumulate (statistics.py)       the statistics ops (core/train/strategy.py)
    bin_tiles(bounds, visible, order, height, width) (binning.py) the per-tile depth-ordered lists
The kernels themselves: prepare_kernels.py, binning_kernels.py, gaussian_kernels.py and
neural_kernels.py (the tile walk they share in tiles.py), statistics_kernels.py, loss_kernels.py,
positivity_kernels.py; what their launchers share: launch.py.

Why Triton: its JIT compiles the kernels on a user's first GPU run with no nvcc and nothing to
download (the wheel ships its compiler), and `TRITON_INTERPRET=1` runs the very same kernels on
CPU tensors, so CI (no GPU) tests them against the torch twins on tiny views (tests/test_triton.py).

The design is gsplat's/3DGS's. Per view:
1. the kind's per-view preparation (preparation.py), one lane per primitive, forward and
   hand-written backward (prepare_kernels.py; the twins: `twin_view` of kinds/gaussian.py and kinds/neural.py, and
   core/splat/sh.py): the colours from the SH; for Gaussians the EWA projection (mean2d, the conic
   with the 0.3 px² blur) and the 3σ boxes in one launch; for neural primitives the dual-conic
   boxes, then the ellipsoid frame M R_cam, o′, ω0 W1 R_cam, the phases c_k and 1/max s ((W2, b2)
   stay torch: an edited model's rest metric scales them);
2. the depth order (a stable torch sort, as the twin) and the tile binning (binning.py around
   binning_kernels.py): every visible primitive × the 16×16 tiles its box touches, keys (tile,
   depth rank) written by one lane per primitive and sorted by torch.sort, per-tile [start, end)
   ranges of primitive indices. The host reads the device once a view, for
   the number of those pairs (the size of the key array, as 3DGS and gsplat read it): every
   primitive keeps its place in the order, the invisible ones after the visible, so that nothing
   else waits for a count;
3. two Triton launches (views.py around gaussian_kernels.py, neural_kernels.py; the tile walk
   they share in tiles.py): the forward, one program per tile compositing front to back with early termination,
   and the backward, walking each pixel's list back to front from its final T with atomic adds of
   the per-primitive gradients. The kernels read the primitives through the lists: nothing is
   gathered into depth order, nothing is stored per pair, and the launches per view do not depend
   on the primitive count.
The population-control statistics come out of autograd as on every path: the means' gradient
(Gaussians) and the MLP's gradients (neural) are what the strategies read (core/train/strategy.py),
one more launch a view (statistics.py around statistics_kernels.py). The step's image loss,
(1 − λ) L1 + λ D-SSIM, is four more (loss.py around loss_kernels.py, two each way); the
neural kind's non-negative density projection after Adam one (positivity.py).

Where it runs: CUDA tensors (float32, float64) when Triton ≥ MIN_TRITON is installed and a GPU is
present (otherwise CUDA runs the torch twins, and `--device cuda` warns: cli/common.py); CPU
tensors only with the interpreter on (TRITON_INTERPRET=1 before triton is imported) AND the backend
chosen explicitly with `backends.using("triton")`, so that the CPU path never changes by itself.
Triton is imported at the first view drawn here, never at start-up.
"""

from __future__ import annotations

import functools
import importlib.util
import re

import torch

from radfield.core.backends.seam import chosen
from radfield.core.backends.gpu.binning import bin_tiles, pair_count
from radfield.core.backends.gpu.launch import (COMPILE_OPTIONS, NEURAL_BACKWARD_OPTIONS, PREPARE_OPTIONS, TILE,
                                               interpreting)
from radfield.core.backends.gpu.loss import photometric
from radfield.core.backends.gpu.positivity import project_nonnegative_
from radfield.core.backends.gpu.preparation import neural_bounds, sh_color
from radfield.core.backends.gpu.statistics import gaussian_accumulate, neural_accumulate
from radfield.core.backends.gpu.views import gaussian_view, neural_view

NAME = "triton"
__all__ = ["NAME", "TILE", "COMPILE_OPTIONS", "NEURAL_BACKWARD_OPTIONS", "PREPARE_OPTIONS", "runs", "why_not",
           "interpreting", "bin_tiles", "pair_count", "gaussian_view", "neural_view", "sh_color", "neural_bounds",
           "neural_accumulate", "gaussian_accumulate", "photometric", "project_nonnegative_"]


# the oldest Triton the kernels compile with (3.3 cannot return nested tuples from a jit function:
# neural_kernels.py's per-unit terms); checked against 3.4.0, 3.5.1, 3.6.0, 3.7.1 and 3.9.0
MIN_TRITON = (3, 4)


@functools.cache
def _version() -> tuple[int, ...] | None:
    """The installed Triton's (major, minor), from its metadata (triton is not imported), or None."""
    import importlib.metadata

    if importlib.util.find_spec("triton") is None:
        return None
    try:
        release = importlib.metadata.version("triton")
    except importlib.metadata.PackageNotFoundError:   # importable but not installed by pip: trust it
        return MIN_TRITON
    return _release(release)


def _release(text: str) -> tuple[int, ...]:
    """(major, minor) of a version string such as "3.6.0" or "2.5.2.dev0"."""
    return tuple(int(part) for part in re.findall(r"\d+", text)[:2])


def _dotted(version: tuple[int, ...]) -> str:
    return ".".join(map(str, version))


def _installed() -> bool:
    version = _version()
    return version is not None and version >= MIN_TRITON


def _chosen() -> bool:
    return chosen() == NAME


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
    version = _version()
    if version is None:
        return "triton is not installed"
    if version < MIN_TRITON:
        return f"triton {_dotted(version)} is older than {_dotted(MIN_TRITON)}, the oldest the kernels compile with"
    if torch.cuda.is_available():
        return None
    if not interpreting():
        return "no CUDA GPU (and TRITON_INTERPRET is not set)"
    numpy = _numpy_version()
    if version < INTERPRETER_WITH_NUMPY_2_5 and numpy >= (2, 5):
        return (f"the interpreter of triton {_dotted(version)} cannot run the kernels with numpy {_dotted(numpy)} "
                "(Triton 3.8 can, as can numpy before 2.5)")
    return None


# Triton's interpreter before 3.8 takes a one-element reduction used as a loop bound through
# int(array), which numpy 2.5 refuses (3.8 squeezes the array first): the tests' CPU mode only
INTERPRETER_WITH_NUMPY_2_5 = (3, 8)


def _numpy_version() -> tuple[int, ...]:
    import numpy

    return _release(numpy.__version__)
