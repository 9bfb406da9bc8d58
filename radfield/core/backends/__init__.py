"""The kernel-backend seam: which implementation of a kernel runs, per device, dtype and kind.

Every kernel of the renderer, the loss and population control has a readable torch twin next to
its call site (core/render/, core/train/losses.py, strategy.py, positivity.py) and may have faster
implementations in backends. This module is the one place that decides which one runs:

    backends.kernel(op, device, dtype)   the implementation of `op` from the best backend that runs
                                         tensors of (device, dtype) and implements it; None: the
                                         caller runs its torch twin
    backends.available(device, dtype, kind=None)   the backends usable here, best first ("torch" last;
                                         with `kind`: those that render it)
    backends.select(device, dtype, kind=None)      the first of them

Backends, best first:
- "fused-cpu": the C++/OpenMP ops of core/backends/fused.py (csrc/), for CPU float32/float64
  tensors, when the extension builds (it is compiled at first use; a failed build warns once);
- "triton": the Triton kernels of core/backends/gpu/ (issue 27), for CUDA tensors, and for CPU
  tensors only under TRITON_INTERPRET=1 inside using("triton") (tests/test_triton.py);
- "torch": the twins, on every device and dtype.
Another backend registers itself where it belongs in that order (`register(Backend(name, runs=...,
rank=...))`: lower ranks are tried first) and its ops with `implement(op, name, fn)`; a kind registers its whole-view renderer for a
backend as op `view_op(kind)`, "view.<kind>" (kinds/neural.py, kinds/gaussian.py). No call site changes.

The ops are the keys of `Op` (an unknown key is refused) and their signatures those of the
fused-cpu functions registered at the bottom (the call sites document their twins): sh_color, sh_color_parts (core/render/rasterize.py), relight_view_dc
(core/kinds/relight.py: view_sh), ssim_map, photometric, anisotropy (core/train/losses.py),
neural_accumulate, gaussian_accumulate (core/train/strategy.py), project_nonnegative_
(core/train/positivity.py), and view.<kind>:
(prims, frame, colors, t_min) -> (Σ w c, Σ w z, T, counters (evaluated, composited, terminated,
candidate pairs: a tensor, or a function that makes it), the number of visible primitives (an
int, or a 0-dim tensor); the counts are read only if someone asks, core/render/rasterize.py:
RenderCounts).

One switch forces the twins everywhere: `RADFIELD_KERNELS=torch` (read at every call). `using(name)`
restricts the choice to one backend within a block (tests and benchmarks compare them).
"""

from radfield.core.backends.seam import (FUSED_CPU, TORCH, TRITON, Backend, Op, available, chosen, forced_torch,
                                         implement, kernel, names, register, select, unregister, using, view_op, why_not)

__all__ = ["FUSED_CPU", "TORCH", "TRITON", "Backend", "Op", "available", "chosen", "forced_torch", "implement", "kernel",
           "names", "register", "select", "unregister", "using", "view_op", "why_not"]

# --- the fused CPU kernels ------------------------------------------------------------------------

from radfield.core.backends import fused  # noqa: E402

register(Backend(FUSED_CPU, fused.available, fused.build_error, rank=10))
for _op in Op:   # fused.py implements every op (its functions are named by the ops)
    implement(_op, FUSED_CPU, getattr(fused, _op.value))
del _op

# --- the Triton GPU kernels (core/backends/gpu/; triton is imported at the first view drawn) ----------
# ranked after fused-cpu, which changes nothing: fused-cpu never runs CUDA tensors, and triton
# runs CPU tensors only inside using("triton") (its tests), where no other backend is offered
from radfield.core.backends import gpu  # noqa: E402

register(Backend(TRITON, gpu.runs, gpu.why_not, rank=20))
for _op in (Op.SH_COLOR, Op.NEURAL_ACCUMULATE, Op.GAUSSIAN_ACCUMULATE, Op.PHOTOMETRIC, Op.PROJECT_NONNEGATIVE):
    implement(_op, TRITON, getattr(gpu, _op.value))
del _op
