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
Another backend registers itself where it belongs in that order (`register(Backend(name, runs=...),
before=...)`) and its ops with `implement(op, name, fn)`; a kind registers its whole-view renderer for a
backend as op "view.<kind>" (kinds/neural.py, kinds/gaussian.py). No call site changes.

The ops and their signatures are those of the fused-cpu functions registered at the bottom (the
call sites document their twins): sh_color, sh_color_parts (core/render/rasterize.py), relight_view_dc
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

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from dataclasses import dataclass

import torch

TORCH = "torch"
FUSED_CPU = "fused-cpu"
TRITON = "triton"


@dataclass(frozen=True)
class Backend:
    """A family of kernel implementations. runs(device, dtype): whether it can run tensors of that
    device (None: any) and dtype (None: any) on this machine (it may build itself on the first call);
    why_not(): the reason it cannot run at all, or None."""

    name: str
    runs: Callable[[torch.device | str | None, torch.dtype | None], bool]
    why_not: Callable[[], str | None] = lambda: None


_BACKENDS: list[Backend] = [Backend(TORCH, lambda device, dtype: True)]   # best first, the twins last
_OPS: dict[str, dict[str, Callable]] = {}                                 # op -> {backend: implementation}
_ONLY: list[str] = []                                                     # using(): the innermost restriction


def forced_torch() -> bool:
    """RADFIELD_KERNELS=torch: every kernel runs its torch twin."""
    return os.environ.get("RADFIELD_KERNELS", "").strip().lower() == TORCH


def register(backend: Backend, *, before: str = TORCH) -> None:
    """Add a backend, preferred to `before` and to every backend after it."""
    if any(b.name == backend.name for b in _BACKENDS):
        raise ValueError(f"backend {backend.name!r} is registered already")
    names = [b.name for b in _BACKENDS]
    _BACKENDS.insert(names.index(before), backend)


def unregister(name: str) -> None:
    """Remove a backend and its ops (never the torch twins)."""
    if name == TORCH:
        raise ValueError("the torch twins cannot be unregistered")
    _BACKENDS[:] = [b for b in _BACKENDS if b.name != name]
    for table in _OPS.values():
        table.pop(name, None)


def implement(op: str, backend: str, fn: Callable) -> None:
    """Register `fn` as backend's implementation of `op` (the twin itself is never registered)."""
    if backend == TORCH:
        raise ValueError("the torch twins live at their call sites; register other backends' kernels")
    _OPS.setdefault(op, {})[backend] = fn


def names() -> list[str]:
    """Every registered backend, best first."""
    return [b.name for b in _BACKENDS]


def why_not(name: str) -> str | None:
    """Why a backend cannot run at all here (RADFIELD_KERNELS=torch, a failed build, ...), or None."""
    if name == TORCH:
        return None
    if forced_torch():
        return "RADFIELD_KERNELS=torch"
    backend = next((b for b in _BACKENDS if b.name == name), None)
    return f"no backend {name!r}" if backend is None else backend.why_not()


def available(device: torch.device | str | None = None, dtype: torch.dtype | None = None,
              kind: str | None = None) -> list[str]:
    """The backends that run tensors of (device, dtype) here, best first, ending with "torch";
    with `kind`, only those that also render that primitive kind (op "view.<kind>")."""
    if forced_torch():
        return [TORCH]
    out = []
    for backend in _BACKENDS:
        if backend.name == TORCH:
            break
        if _ONLY and backend.name != _ONLY[-1]:
            continue
        if kind is not None and backend.name not in _OPS.get(f"view.{kind}", {}):
            continue
        if backend.runs(device, dtype):
            out.append(backend.name)
    return out + [TORCH]


def select(device: torch.device | str | None = None, dtype: torch.dtype | None = None, kind: str | None = None) -> str:
    """The backend that runs here: the first of `available`."""
    return available(device, dtype, kind)[0]


def kernel(op: str, device: torch.device | str | None, dtype: torch.dtype | None) -> Callable | None:
    """The implementation of `op` for tensors of (device, dtype): the best available backend's
    that implements it, or None when the caller's torch twin runs."""
    table = _OPS.get(op)
    if not table:
        return None
    for name in available(device, dtype):
        if name in table:
            return table[name]
    return None


def chosen() -> str | None:
    """The backend the innermost `using()` restricts to, or None."""
    return _ONLY[-1] if _ONLY else None


@contextlib.contextmanager
def using(name: str):
    """Within the block only backend `name` (and the torch twins, for what it does not implement)
    runs; using("torch") runs the twins alone."""
    if name not in names():
        raise ValueError(f"unknown backend {name!r} (registered: {', '.join(names())})")
    _ONLY.append(name)
    try:
        yield
    finally:
        _ONLY.pop()


# --- the fused CPU kernels ------------------------------------------------------------------------

from radfield.core.backends import fused  # noqa: E402  (fused reads forced_torch from here)

register(Backend(FUSED_CPU, fused.available, fused.build_error))
for _op in ("sh_color", "sh_color_parts", "relight_view_dc", "ssim_map", "photometric", "anisotropy",
            "neural_accumulate", "gaussian_accumulate", "project_nonnegative_"):
    implement(_op, FUSED_CPU, getattr(fused, _op))
del _op

# --- the Triton GPU kernels (core/backends/gpu/; triton is imported at the first view drawn) ----------
# after fused-cpu in the list, which changes nothing: fused-cpu never runs CUDA tensors, and triton
# runs CPU tensors only inside using("triton") (its tests), where no other backend is offered
from radfield.core.backends import gpu  # noqa: E402

register(Backend(TRITON, gpu.runs, gpu.why_not))
for _op in ("sh_color", "neural_accumulate", "gaussian_accumulate", "photometric", "project_nonnegative_"):
    implement(_op, TRITON, getattr(gpu, _op))
del _op
