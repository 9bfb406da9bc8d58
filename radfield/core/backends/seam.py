"""The seam's registry (the package's docstring says what it decides): the backends, best first
(a `Registry` ordered by each backend's `rank`, the torch twins always last), the ops each
implements, the switch that forces the twins, and `using()`. The backends register with it in the
package (core/backends/__init__.py); fused.py and gpu/ read the switch from here."""

from __future__ import annotations

import contextlib
import enum
import os
from collections.abc import Callable
from dataclasses import dataclass

import torch

from radfield.util.registry import Registry

TORCH = "torch"
FUSED_CPU = "fused-cpu"
TRITON = "triton"


class Op(enum.StrEnum):
    """The ops a backend may implement (signatures: the package's docstring). A key that is not one
    of these, nor a kind's view op (`view_op`), is refused by `implement` and `kernel`: a misspelt
    op fails at once instead of quietly running the twin."""

    SH_COLOR = "sh_color"
    SH_COLOR_PARTS = "sh_color_parts"
    RELIGHT_VIEW_DC = "relight_view_dc"
    SSIM_MAP = "ssim_map"
    PHOTOMETRIC = "photometric"
    ANISOTROPY = "anisotropy"
    NEURAL_ACCUMULATE = "neural_accumulate"
    GAUSSIAN_ACCUMULATE = "gaussian_accumulate"
    PROJECT_NONNEGATIVE = "project_nonnegative_"


_OP_NAMES = frozenset(Op)
VIEW_PREFIX = "view."


def view_op(kind: str) -> str:
    """The op of a primitive kind's whole-view renderer (forward and backward of one view)."""
    return VIEW_PREFIX + kind


def _checked(op: str) -> str:
    if op in _OP_NAMES or (op.startswith(VIEW_PREFIX) and len(op) > len(VIEW_PREFIX)):
        return op
    raise KeyError(f"unknown backend op {op!r} (ops: {', '.join(Op)}, or view.<kind>)")


@dataclass(frozen=True)
class Backend:
    """A family of kernel implementations. runs(device, dtype): whether it can run tensors of that
    device (None: any) and dtype (None: any) on this machine (it may build itself on the first call);
    why_not(): the reason it cannot run at all, or None; rank: its place in the order backends are
    tried, lowest first (fused-cpu 10, triton 20; equal ranks keep their registration order; the
    torch twins come last whatever their rank)."""

    name: str
    runs: Callable[[torch.device | str | None, torch.dtype | None], bool]
    why_not: Callable[[], str | None] = lambda: None
    rank: int = 50


# best first, the twins last
_BACKENDS: Registry[Backend] = Registry("backend", order=lambda backend: (backend.name == TORCH, backend.rank))
_BACKENDS.register(TORCH, Backend(TORCH, lambda device, dtype: True))
_OPS: dict[str, dict[str, Callable]] = {}                                 # op -> {backend: implementation}
_ONLY: list[str] = []                                                     # using(): the innermost restriction


def forced_torch() -> bool:
    """RADFIELD_KERNELS=torch: every kernel runs its torch twin."""
    return os.environ.get("RADFIELD_KERNELS", "").strip().lower() == TORCH


def register(backend: Backend) -> Backend:
    """Add a backend at its place in the order (its `rank`) and return it; ValueError when its
    name is taken."""
    return _BACKENDS.register(backend.name, backend)


def unregister(name: str) -> None:
    """Remove a backend and its ops (never the torch twins)."""
    if name == TORCH:
        raise ValueError("the torch twins cannot be unregistered")
    _BACKENDS.unregister(name)
    for table in _OPS.values():
        table.pop(name, None)


def implement(op: str, backend: str, fn: Callable) -> None:
    """Register `fn` as backend's implementation of `op` (the twin itself is never registered)."""
    if backend == TORCH:
        raise ValueError("the torch twins live at their call sites; register other backends' kernels")
    _OPS.setdefault(_checked(op), {})[backend] = fn


def names() -> list[str]:
    """Every registered backend, best first."""
    return list(_BACKENDS.names())


def why_not(name: str) -> str | None:
    """Why a backend cannot run at all here (RADFIELD_KERNELS=torch, a failed build, ...), or None."""
    if name == TORCH:
        return None
    if forced_torch():
        return "RADFIELD_KERNELS=torch"
    return _BACKENDS.get(name).why_not() if name in _BACKENDS else f"no backend {name!r}"


def available(device: torch.device | str | None = None, dtype: torch.dtype | None = None,
              kind: str | None = None) -> list[str]:
    """The backends that run tensors of (device, dtype) here, best first, ending with "torch";
    with `kind`, only those that also render that primitive kind (op "view.<kind>")."""
    if forced_torch():
        return [TORCH]
    out = []
    for backend in _BACKENDS.values():
        if backend.name == TORCH:
            break
        if _ONLY and backend.name != _ONLY[-1]:
            continue
        if kind is not None and backend.name not in _OPS.get(view_op(kind), {}):
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
    if table is None:
        _checked(op)   # an op nobody implements runs its twin; a misspelt one is an error
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
