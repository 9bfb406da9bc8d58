"""Measure what render() keeps for backward: the bytes of the tensors autograd saves, per
pixel-primitive pair, for several max_pairs (it does not depend on max_pairs: every chunk's saved
tensors live until backward). Usage: OMP_NUM_THREADS=1 .venv/bin/python scripts/saved_memory.py [torch|fused]"""

import sys

import torch

from radfield.bench.render import bench_cameras, bench_scene
from radfield.core.backends import fused
from radfield.core.render.rasterize import render


def saved_bytes(prims, camera, max_pairs: int) -> tuple[int, dict]:
    storages: dict[int, int] = {}

    def pack(t):  # each storage counted once, however many views of it are saved
        storage = t.untyped_storage()
        storages[storage.data_ptr()] = max(storages.get(storage.data_ptr(), 0), storage.nbytes())
        return t

    params = prims.map(lambda t: t.clone().requires_grad_(True))
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = render(params, camera, max_pairs=max_pairs)
    return sum(storages.values()), out.meta


if __name__ == "__main__":
    if sys.argv[1:] == ["torch"]:
        fused.available = lambda *args, **kwargs: False  # the torch reference kernels
    neural, gauss = bench_scene(3000)
    camera = bench_cameras(1, 128, 128)[0]
    print(f"kernels: {'fused' if fused.available(torch.device('cpu'), torch.float32) else 'torch'}")
    for name, prims in (("neural", neural), ("gaussian", gauss)):
        for max_pairs in (1 << 10, 1 << 14, 1 << 20):
            saved, meta = saved_bytes(prims, camera, max_pairs)
            print(f"{name:8s} max_pairs={max_pairs:8d}: saved for backward {saved / 1e6:6.1f} MB = "
                  f"{saved / meta['candidate_pairs']:5.0f} B per candidate pair ({meta['candidate_pairs']} pairs)")
