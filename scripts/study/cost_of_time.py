"""The cost of time or of light on a shared machine (issues 29, 30): loop.train's ms per step of
the static and the time-conditioned (or relightable) kinds at bench-train's scene (10k primitives,
4 orbit views, each kind at its models' SH degree: 3, the relightable kinds' 0), measured in the
calling thread's CPU time (with OMP_NUM_THREADS=1 the fused kernels, autograd and Adam all run in
it), the kinds interleaved, REPS runs each, the minimum kept. bench-train's wall clock swings by
±40 % when other jobs share the 2 cores; this one agrees with itself to a few per cent.
    usage: OMP_NUM_THREADS=1 .venv/bin/python scripts/study/cost_of_time.py [SIZE] [REPS] [STEPS] [CONDITION]
(defaults 64 7 20 dynamic; CONDITION `relight` for the cost of light). Prints each kind's minimum and
median and the conditioned/static ratios of the minima."""
import sys
import time

import torch

from radfield.bench.render import bench_cameras, bench_models
from radfield.bench.train import _targets, bench_config
from radfield.core.trainer import loop

CONDITIONS = ("dynamic", "relight")   # the kinds neural-<condition>, gaussian-<condition>
WARMUP = 2


def cpu_ms_per_step(prims, cams, images, steps: int) -> float:
    """loop.train's thread CPU ms per step after WARMUP steps (bench-train's train() column, in CPU time)."""
    cfg = bench_config(WARMUP + steps)
    cfg["sh_degree"], cfg["sh_increase_every"] = prims.sh_degree, 1   # the model's own degree from step 3 on, as bench-train's train()
    clock = []
    loop.train(prims, cams, images, cfg, background=(1.0, 1.0, 1.0), extent=1.0, seed=0,
                  on_step=lambda step, info: clock.append(time.thread_time()))
    return 1e3 * (clock[-1] - clock[WARMUP - 1]) / steps


def main(size: int = 64, reps: int = 7, steps: int = 20, condition: str = "dynamic") -> None:
    if condition not in CONDITIONS:
        sys.exit(f"CONDITION must be one of {', '.join(CONDITIONS)}, got {condition!r}")
    kinds = ("neural", f"neural-{condition}", "gaussian", f"gaussian-{condition}")
    scenes = {}
    for kind in kinds:
        prims = bench_models(10_000, (kind,))[kind]
        cams = bench_cameras(4, size, size)
        scenes[kind] = (prims, cams, _targets(prims, cams, "cpu"))
    runs = {kind: [] for kind in kinds}
    for _ in range(reps):
        for kind in kinds:   # interleaved: a busy spell of the machine touches every kind alike
            runs[kind].append(cpu_ms_per_step(*scenes[kind], steps))
    print(f"cost of {condition}: {size}x{size}, 10000 primitives, {reps} runs of {steps} steps, thread CPU ms per step, "
          f"threads={torch.get_num_threads()}")
    for kind in kinds:
        print(f"  {kind:17s} min {min(runs[kind]):7.2f}   median {sorted(runs[kind])[reps // 2]:7.2f}")
    for kind in ("neural", "gaussian"):
        print(f"  {kind}-{condition} / {kind}: {min(runs[f'{kind}-{condition}']) / min(runs[kind]):.3f}x")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:4]), *sys.argv[4:5])
