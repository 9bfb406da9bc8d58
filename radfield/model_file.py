"""The model file: one safetensors file, documented in docs/formats.md ("The model file").

Every kind: float32 `means` (P,3), `log_scales` (P,3), `quats` (P,4, w x y z), the kind's own
tensors, `sh` (P,K,3); metadata format=radfield, kind, version, sh_degree, and what the kind writes
(radfield.core.kinds: its `schema`, `optional`, `write_metadata` and `read_metadata` say it).
Neural primitives: `w1` (P,N,3), `b1` (P,N), `w2` (P,N), `b2` (P,), optional `rest_metric` (P,6);
metadata omega0, and `window` ("1", written only when set; absent means "0"): the density window
of render.window (`prims.window`, core/kinds/neural_density.py: density_window). Gaussians: `opacities`
(P,) logits. Every kind: optional metadata `supersample` (an integer 1..4 as a string, written only
when > 1; absent means 1): the rays per pixel side the model was trained with (render.supersample),
carried as `prims.supersample` and honoured by every render of the model (core/render/antialias.py: render_model).
Tensors may also be stored as float16 (`radfield bake --fp16` writes all of them so); readers
accept float32 and float16 and return float32. Readers check everything and never
unpickle anything.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save

from radfield.core import kinds
from radfield.core.kinds.base import int_metadata
from radfield.util.atomic import atomic_write_bytes
from radfield.errors import RadfieldError
from radfield.core.splat.sh import num_sh_coeffs

FORMAT = "radfield"
VERSION = 1
MAX_SUPERSAMPLE = 4  # render.supersample's range (stages/init.py checks the config alike)


STORAGE_DTYPES = (torch.float32, torch.float16)


def save_model(path: str | Path, prims: kinds.Primitives, extra: dict | None = None,
               dtype: torch.dtype = torch.float32) -> None:
    """Write `prims` as float32 (or float16) safetensors, atomically (temporary file, then rename).
    `extra` adds string metadata (e.g. the scene normalisation as JSON)."""
    path = Path(path)
    if dtype not in STORAGE_DTYPES:
        raise ValueError(f"model files store float32 or float16, not {dtype}")
    tensors = {k: v.detach().to("cpu", dtype).contiguous() for k, v in prims.tensors().items()}
    for name, t in tensors.items():
        if dtype == torch.float16 and torch.isinf(t).any() and torch.isfinite(getattr(prims, name)).all():
            raise RadfieldError(f"{path}: tensor {name!r} has values beyond the float16 range (store float32)")
    meta = {"format": FORMAT, "kind": prims.kind, "version": str(VERSION), "sh_degree": str(prims.sh_degree)}
    meta.update(kinds.of(prims).write_metadata(prims))
    if prims.supersample != 1:  # absent = 1: a model trained without it keeps its bytes (and hash)
        meta["supersample"] = str(int(prims.supersample))
    meta.update({k: v if isinstance(v, str) else json.dumps(v) for k, v in (extra or {}).items()})
    atomic_write_bytes(path, _canonical_header(save(tensors, metadata=meta)))


def _canonical_header(blob: bytes) -> bytes:
    """The same safetensors file with its JSON header keys sorted. safetensors writes metadata in
    hash-map order, so equal models would give different bytes, and the stage cache (which hashes
    file contents) would see a change that is not there."""
    n = int.from_bytes(blob[:8], "little")
    header = json.dumps(json.loads(blob[8 : 8 + n]), separators=(",", ":"), sort_keys=True).encode()
    header += b" " * (-len(header) % 8)  # the format pads the header with spaces to 8-byte alignment
    return len(header).to_bytes(8, "little") + header + blob[8 + n :]


def read_metadata(path: str | Path) -> dict[str, str]:
    try:
        with safe_open(str(path), framework="pt") as f:
            return dict(f.metadata() or {})
    except (SafetensorError, OSError, ValueError) as e:
        raise RadfieldError(f"{path}: not a readable safetensors file ({_first_line(e)})") from None


def load_model(path: str | Path, device: str | torch.device = "cpu") -> kinds.Primitives:
    """Read and validate a model file; every problem is a RadfieldError naming the file and field."""
    path = Path(path)
    if not path.is_file():
        raise RadfieldError(f"{path}: no such model file")
    meta = read_metadata(path)
    if meta.get("format") != FORMAT:
        raise RadfieldError(f"{path}: metadata format is {meta.get('format')!r}, expected {FORMAT!r} (not a radfield model)")
    if meta.get("version") != str(VERSION):
        raise RadfieldError(f"{path}: format version {meta.get('version')!r} is not supported (this radfield reads version {VERSION})")
    if meta.get("kind") not in kinds.names():
        raise RadfieldError(f"{path}: metadata kind is {meta.get('kind')!r}, expected one of {sorted(kinds.names())}")
    kind = kinds.get(meta["kind"])
    sh_degree = int_metadata(path, meta, "sh_degree")
    if not 0 <= sh_degree <= 3:
        raise RadfieldError(f"{path}: metadata sh_degree={sh_degree} is outside 0..3")
    supersample = int_metadata(path, meta, "supersample") if "supersample" in meta else 1
    if not 1 <= supersample <= MAX_SUPERSAMPLE:
        raise RadfieldError(f"{path}: metadata supersample={supersample} is outside 1..{MAX_SUPERSAMPLE}")
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            names = set(f.keys())
            schema = kind.schema()
            schema.update({name: tail for name, tail in kind.optional.items() if name in names})
            missing, unknown = sorted(set(schema) - names), sorted(names - set(schema))
            if missing or unknown:
                what = "; ".join(s for s in (f"missing tensors {missing}" if missing else "",
                                             f"unexpected tensors {unknown}" if unknown else "") if s)
                raise RadfieldError(f"{path}: {what} for kind={kind.name}")
            tensors = {name: f.get_tensor(name) for name in schema}
    except SafetensorError as e:
        raise RadfieldError(f"{path}: corrupt tensor data ({_first_line(e)})") from None

    # P is what most tensors agree on, so the message names the odd one out
    leading = [t.shape[0] if t.ndim else -1 for t in tensors.values()]
    num = max(set(leading), key=leading.count)
    dims = {"K": num_sh_coeffs(sh_degree), **_widths(schema, tensors)}
    for name, tail in schema.items():
        t = tensors[name]
        expected = (num,) + tuple(dims[d] if isinstance(d, str) else d for d in tail)
        if t.dtype not in STORAGE_DTYPES:
            raise RadfieldError(f"{path}: tensor {name!r} has dtype {str(t.dtype).removeprefix('torch.')}, "
                                f"expected float32 or float16")
        if tuple(t.shape) != expected:
            shape = "(" + ", ".join("P" if i == 0 else str(x) for i, x in enumerate(expected)) + ")"
            raise RadfieldError(f"{path}: tensor {name!r} has shape {tuple(t.shape)}, expected {shape} with P={num}"
                                + (f", K={dims['K']} for sh_degree={sh_degree}" if name == "sh" else ""))
        bad = ~torch.isfinite(t)
        if bad.any():
            row = int(torch.nonzero(bad)[0, 0])
            raise RadfieldError(f"{path}: tensor {name!r} holds {int(bad.sum())} NaN/Inf values (first at primitive {row})")
    tensors = {name: t.to(torch.float32) for name, t in tensors.items()}
    model = kind.assemble(tensors, kind.read_metadata(path, meta), supersample=supersample)
    if (model.quats == 0).all(-1).any():   # exactly zero; tiny norms are check_values' (|q|² underflows)
        raise RadfieldError(f"{path}: tensor 'quats' has all-zero rows (no rotation)")
    # finite is not enough: e.g. log_scales = 100 (s = inf in float32) rendered as background
    out_of_range = kind.check_values(model)
    if out_of_range is not None:
        name, row, why = out_of_range
        raise RadfieldError(f"{path}: tensor {name!r} is out of range at primitive {row} ({why})")
    return model.to(device)


def _widths(schema: dict[str, tuple], tensors: dict[str, torch.Tensor]) -> dict[str, int | None]:
    """The value of each width letter of a schema other than K (neural: N, the MLP width), read off
    the first tensor that has it (None when that tensor has the wrong rank: its check reports it)."""
    widths = {}
    for name, tail in schema.items():
        for axis, dim in enumerate(tail):
            if isinstance(dim, str) and dim != "K" and dim not in widths:
                t = tensors[name]
                widths[dim] = t.shape[1 + axis] if t.ndim == 1 + len(tail) else None
    return widths


def _first_line(e: Exception) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]
