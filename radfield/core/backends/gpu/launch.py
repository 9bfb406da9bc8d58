"""What the Triton backend's launchers share (core/backends/gpu/): the compile options, the tile
side, the error line of a kernel that fails on this machine, and the units' padded axis."""

from __future__ import annotations

import contextlib
import os

from radfield.errors import RadfieldError

TILE = 16   # tile side in pixels (gaussian_kernels.SIDE)
# The kernels' compile options. No FMA contraction (as the fused CPU build, -ffp-contract=off): the
# backward recomputes each pair's α exactly as the forward did, whatever instructions the compiler
# picks in either kernel. 8 warps: one thread per pixel of a 16×16 tile, as 3DGS's rasteriser; with
# 4 (two pixels a thread) the windowed neural backward needs more than 255 registers and spills.
# ptxas for sm_90 with 8 warps: 32/40 registers for the Gaussian forward/backward, 77/103 for the
# neural forward and 128/214 for its backward, hard-edged/windowed (tests/test_triton.py checks
# that no float32 kernel spills; scripts/kernel_report.py prints these figures).
COMPILE_OPTIONS = {"enable_fp_fusion": False, "num_warps": 8}
# The neural backward's, by WINDOW. Left to itself ptxas fits the hard-edged one in 128 registers
# (two blocks an SM) by spilling 20 bytes a thread; capped at 160 it fits them without spilling.
# The windowed one takes 214 (one block an SM) either way.
NEURAL_BACKWARD_OPTIONS = {False: {**COMPILE_OPTIONS, "maxnreg": 160}, True: COMPILE_OPTIONS}
# the per-primitive kernels (prepare_kernels.py): 4 warps for their 128 primitives a program; no FMA
# contraction either, so that the backward's recomputed sums take the forward's clamp
PREPARE_OPTIONS = {"enable_fp_fusion": False, "num_warps": 4}


def interpreting() -> bool:
    """TRITON_INTERPRET=1: triton runs its kernels on CPU tensors (numpy), slowly: the tests' mode."""
    return os.environ.get("TRITON_INTERPRET", "").strip() in ("1", "true", "True")


@contextlib.contextmanager
def launching():
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


def padded(units: int) -> int:
    """The hidden units' axis in the kernels: a power of two (the padding is masked)."""
    return max(1 << (units - 1).bit_length(), 1)
