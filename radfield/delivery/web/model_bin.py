"""model.bin, the model as the browser renderer reads it (docs/formats.md, "The web export").

A safetensors file with the model file's tensors (names and shapes as radfield's model file,
radfield/model_file.py) and metadata (format "radfield-web", version, kind, sh_degree, supersample,
what the kind writes: omega0 and window, time_frequency), in one of two precisions:

- compact: every float tensor float16, the means 16-bit fixed point in the model's bounding box
  (mean = min + (max − min) q / 65535, `means_min`/`means_max` in the metadata) and the rotations
  as their "smallest three" (the unit quaternion's components but its largest, `quats` (P, 3)
  float16, that one positive, its index in `quats_index` (P,) uint8), under half the bytes of the
  float32 model file: float16 means would move a primitive by up to 2⁻¹¹ of its coordinate
  (0.8 px at 800 px across a unit object), 16 bits over the box by 1/131070 of it;
- float32: the model file's numbers.

`web_precision` keeps the compact one where its render stays close to the float32 model's
(`HALF_MIN_PSNR`), and `decoded` gives the model the page draws, for that check and the tests.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import torch
from safetensors.torch import load as load_safetensors
from safetensors.torch import save as save_safetensors

from radfield.core import kinds

FORMAT = "radfield-web"
VERSION = 1
U16 = 65535
# The compact precision is kept when its render is at least this close to the float32 model's
# (PSNR, dB): an error that far below a model's own error against its photos costs it under 0.1 dB
# for every model up to 40 dB from its photos (independent errors add in MSE: 10^(−Q/10) ≤
# (10^0.01 − 1) 10^(−P/10) ⟺ Q ≥ P + 16.4 dB), and no trained radfield model comes near 40 dB.
HALF_MIN_PSNR = 56.4


def encode(model: kinds.Primitives, compact: bool) -> bytes:
    """model.bin's bytes: float32, or compact (float16, 16-bit means) where `compact`."""
    meta = {"format": FORMAT, "version": str(VERSION), "kind": model.kind, "sh_degree": str(model.sh_degree),
            "supersample": str(int(model.supersample)), **kinds.of(model).write_metadata(model)}
    if "omega0" in meta:
        meta["window"] = "1" if model.window else "0"   # explicit: the page need not know the default
    tensors = {name: t.detach().to("cpu", torch.float32).contiguous() for name, t in model.tensors().items()}
    if compact:
        means = tensors["means"].double()
        low, high = means.amin(0), means.amax(0)
        span = torch.where(high > low, high - low, torch.ones_like(high))
        q = torch.round((means - low) / span * U16).clamp(0, U16).to(torch.int32)
        tensors["means"] = torch.from_numpy(q.numpy().astype(np.uint16))
        meta["means_min"], meta["means_max"] = json.dumps(low.tolist()), json.dumps((low + span).tolist())
        tensors["quats"], tensors["quats_index"] = smallest_three(tensors["quats"])
        for name, t in tensors.items():
            if t.dtype == torch.float32:
                half = t.half()
                # beyond float16's range (±65504) a tensor stays float32 (the page reads both)
                tensors[name] = half if torch.isfinite(half).all() else t
    return save_safetensors(tensors, metadata=meta)


def decoded(model: kinds.Primitives, blob: bytes) -> kinds.Primitives:
    """The model the page draws from model.bin `blob` (written by `encode(model, ...)`): `model`
    with every tensor replaced by the file's numbers, decoded as the page decodes them."""
    tensors = load_safetensors(blob)
    meta = metadata(blob)
    values = {}
    if "quats_index" in tensors:
        tensors["quats"] = from_smallest_three(tensors["quats"].float(), tensors.pop("quats_index"))
    for name, t in tensors.items():
        if t.dtype == torch.uint16:
            low, high = (torch.tensor(json.loads(meta[k]), dtype=torch.float64) for k in ("means_min", "means_max"))
            t = low + (high - low) * t.to(torch.int32).double() / U16
        values[name] = t.to(torch.float32)
    return dataclasses.replace(model, **values)


def metadata(blob: bytes) -> dict[str, str]:
    """The safetensors header's `__metadata__` of `blob`."""
    size = int.from_bytes(blob[:8], "little")
    return json.loads(blob[8:8 + size]).get("__metadata__", {})



def smallest_three(quats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(the three components (P, 3) of each unit quaternion but its largest in magnitude, with the
    sign that makes that one positive, float16; its index (P,) uint8): q and −q are one rotation,
    and the largest is at least 1/2, so √(1 − Σ others²) restores it to float16's precision."""
    q = torch.nn.functional.normalize(quats, dim=-1)
    index = q.abs().argmax(-1)
    q = q * torch.sign(q.gather(-1, index[:, None]))
    keep = torch.ones_like(q, dtype=torch.bool).scatter_(-1, index[:, None], False)
    return q[keep].view(-1, 3).half(), index.to(torch.uint8)


def from_smallest_three(three: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """The unit quaternions (P, 4) of `smallest_three`'s output (the page's decoding)."""
    largest = torch.sqrt(torch.clamp_min(1.0 - (three * three).sum(-1), 0.0))
    index = index.long()
    q = torch.empty(len(three), 4, dtype=three.dtype)
    keep = torch.ones_like(q, dtype=torch.bool).scatter_(-1, index[:, None], False)
    q[keep] = three.reshape(-1)
    q.scatter_(-1, index[:, None], largest[:, None])
    return q
