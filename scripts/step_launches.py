"""The torch ops of a training step on the Triton path, counted on the CPU (no GPU needed): each is
a kernel launch on a GPU, besides the Triton kernels themselves. loop.train on the Triton
backend in Triton's interpreter, 200 primitives, 32×32 views, SH degree 3, one view a step, the
population-control statistics gathered every step (never refined); ops counted below autograd
(the backward's too), without those that launch nothing (views, detaches, allocations) and the
interpreter's own copies of the kernels' arguments, as tests/test_triton.py counts a view's.
Steps 4 and 5 are the steady state (3 and 6 also read the step records). Each kind twice: with
the Triton ops of the loss ("photometric", core/backends/gpu/loss.py) and of the non-negative
density projection ("project_nonnegative_", gpu/positivity.py; neural only), and with their
torch twins.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/step_launches.py"""

from __future__ import annotations

import math
import os
import sys

os.environ["TRITON_INTERPRET"] = "1"   # before anything imports triton

import torch  # noqa: E402
from torch.utils._python_dispatch import TorchDispatchMode  # noqa: E402

from radfield.core import backends, kinds  # noqa: E402
from radfield.core.backends import seam  # noqa: E402
from radfield.core.geometry.cameras import Camera, look_at  # noqa: E402
from radfield.core.kinds import random_gaussians, random_neural  # noqa: E402
from radfield.core.render.rasterize import render  # noqa: E402
from radfield.core.trainer import loop  # noqa: E402
from radfield.pipeline.config import load_defaults  # noqa: E402

NO_KERNEL = {"view", "_unsafe_view", "_reshape_alias", "as_strided", "t", "transpose", "expand", "slice", "select",
             "unsqueeze", "squeeze", "permute", "detach", "alias", "unbind", "split", "split_with_sizes",
             "lift_fresh", "empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided"}


class Launches(TorchDispatchMode):
    """Torch ops by training step (`step` is set by the trainer's first call of each step)."""

    def __init__(self):
        super().__init__()
        self.step = 0
        self.per_step: dict[int, int] = {}

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        frame = sys._getframe(1)
        while frame is not None and frame.f_globals.get("__name__", "").split(".")[0] != "triton":
            frame = frame.f_back
        if frame is None and func.__name__.split(".")[0] not in NO_KERNEL:
            self.per_step[self.step] = self.per_step.get(self.step, 0) + 1
        return func(*args, **(kwargs or {}))


def count(kind: str, cams, images) -> dict[int, int]:
    cfg = load_defaults()["train"]
    cfg.update(iterations=6, batch_views=1, log_every=3, checkpoint_every=100, eval_every=0, sh_degree=3)
    cfg["densify"].update(start=1, stop=100, every=100)
    start = (random_neural if kind == "neural" else random_gaussians)(200, seed=2, sh_degree=3)
    geometry = {name: getattr(start, name) for name in ("means", "log_scales", "quats", "sh")}
    start = kinds.get(kind).from_points(geometry, kinds.get(kind).init_settings(load_defaults()), seed=0)
    decayed = loop.decayed
    launches = Launches()

    def step_marker(lr, ratio, step, iterations):   # the first thing each step does
        launches.step = step + 1
        return decayed(lr, ratio, step, iterations)

    loop.decayed = step_marker
    try:
        with backends.using(backends.TRITON), launches:
            loop.train(start, cams, images, cfg, background=(1.0, 1.0, 1.0), extent=1.0, seed=0, device="cpu")
    finally:
        loop.decayed = decayed
    return launches.per_step


def main() -> None:
    cams = [Camera(fx=41.6, fy=41.6, cx=16, cy=16, width=32, height=32, name=f"v{i}",
                   c2w=look_at((3 * math.cos(i), 3 * math.sin(i), 0.5), (0, 0, 0))) for i in range(3)]
    with torch.no_grad():
        images = torch.stack([render(random_neural(30, seed=1), c).color.clamp(0, 1) for c in cams])
    ops = ("photometric", "project_nonnegative_")
    print("torch ops a training step (steps 4, 5), Triton path")
    for kind in ("neural", "gaussian"):
        for with_ops in (True, False):
            saved = {} if with_ops else {op: seam._OPS[op].pop(backends.TRITON) for op in ops}
            try:
                per_step = count(kind, cams, images)
            finally:
                for op, fn in saved.items():
                    backends.implement(op, backends.TRITON, fn)
            label = "loss, projection on Triton" if with_ops else "on their torch twins"
            print(f"  {kind:8s} {label:28s} {per_step[4]:4d} {per_step[5]:4d}")


if __name__ == "__main__":
    main()
