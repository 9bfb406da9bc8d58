"""Wall-clock timing of device work. CUDA kernels run asynchronously: the clock may only be read
after the device has finished what was queued, or a timing measures the launch, not the work."""

from __future__ import annotations

import time

import torch


def synchronize(device: str | torch.device) -> None:
    """Wait until every kernel queued on `device` has finished (a no-op on the CPU)."""
    device = torch.device(device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def clock(device: str | torch.device) -> float:
    """time.perf_counter() once `device` is idle: the difference of two readings is the device time
    of the work queued in between."""
    synchronize(device)
    return time.perf_counter()
