"""Op "project_nonnegative_" on the Triton backend: the non-negative density projection of the
masked primitives' (W2, b2), in place, one launch (positivity_kernels.py) where the twin
(core/train/positivity.py: project_nonnegative) launches some forty ops; the fused CPU op's
signature."""

from __future__ import annotations

import torch

from radfield.core.backends.gpu.launch import PREPARE_OPTIONS, launching


@torch.no_grad()
def project_nonnegative_(w2: torch.Tensor, b2: torch.Tensor, mask: torch.Tensor) -> None:
    """(W2 (P, N), b2 (P,)) onto ‖W2‖₁ ≤ b2 in place on the rows where the bool mask (P,) is set."""
    from radfield.core.backends.gpu import positivity_kernels as K

    count, units = w2.shape
    if count == 0:
        return
    with launching():
        K.project_nonnegative[(-(-count // K.BLOCK),)](w2, b2, mask.contiguous(), count, UNITS=units, BLOCK=K.BLOCK,
                                                       **PREPARE_OPTIONS)
