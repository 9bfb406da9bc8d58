"""Host tensors onto the device without making the host wait (issue 27).

A blocking copy to a GPU (`tensor.to("cuda")`) first waits for every kernel queued before it
(torch synchronises the stream), so the GPU runs dry while the host launches what follows. An
asynchronous copy from ordinary (pageable) memory is staged at once and waits for nothing, so a
view's few camera numbers travel that way. Reads the other way (device to host) are what the
training loop and the renderer keep out of their steps (core/trainer/loop.py: StepRecords,
core/render/rasterize.py: RenderCounts).
"""

from __future__ import annotations

import functools

import torch


def to_device(host: torch.Tensor, device: torch.device | str, dtype: torch.dtype | None = None) -> torch.Tensor:
    """`host` on `device` in `dtype` (default: its own), queued behind the device's work instead of
    waiting for it; the tensor itself when nothing changes (on the CPU: no copy at all)."""
    return host.to(device=device, dtype=dtype, non_blocking=True)


@functools.lru_cache(maxsize=1024)
def device_constants(values: tuple[float, ...], dtype: torch.dtype, device: torch.device | str) -> torch.Tensor:
    """Numbers a kernel reads, as a (len(values),) tensor of `dtype` on `device`, made once per
    (values, dtype, device) rather than copied every launch (callers never write to it). Made
    outside inference mode: a cached inference tensor could not be saved for a backward."""
    with torch.inference_mode(False):
        return to_device(torch.tensor(values, dtype=dtype), device)
