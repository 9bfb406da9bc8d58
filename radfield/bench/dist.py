"""`radfield bench-dist`: data-parallel training, 1 rank × T threads against R ranks × T/R threads.

The same scene and config for both (bench-render's scene, targets with shifted colours as in
bench-train, `batch_views` views per step, population control gathering statistics every step but
never changing the count): loop.train in this process with T threads, then R ranks started by
torch's elastic launcher (gloo, standalone rendezvous on a free port), one thread each.

A third line, 1 rank × 1 thread, shows what one rank does alone with the whole batch (on a busy
machine several OpenMP threads can be much slower than one). Printed per configuration: steps/s of the timed steps (after `warmup` untimed ones); for the ranks
also the wall time per step inside the all-reduce (radfield.core.trainer.distributed.StepSync: it includes
waiting for the slower rank), the all-reduced bytes per step, and the time of a bare all-reduce of
a buffer that size (communication alone, averaged over 20 calls). On a 2-core machine the point
is correctness and overhead, not speed-up; a shared machine makes every figure noisy.
"""

from __future__ import annotations

import os
import time
import uuid

import torch

from radfield.bench.render import bench_cameras, bench_scene
from radfield.bench.train import _targets, bench_config


def _setup(primitives: int, size: int, views: int, steps: int, batch: int):
    prims = bench_scene(primitives)[0]
    cams = bench_cameras(views, size, size)
    images = _targets(prims, cams, "cpu")
    cfg = bench_config(steps)
    cfg["batch_views"] = batch
    cfg["eval_every"] = 0
    return prims, cams, images, cfg


def _timed_train(prims, cams, images, cfg, warmup: int, world=None) -> float:
    """steps/s of loop.train over the steps after the first `warmup`."""
    from radfield.core.trainer.loop import train

    marks = {}
    train(prims, cams, images, cfg, background=(1.0, 1.0, 1.0), extent=1.0, seed=0, world=world,
          on_step=lambda step, _info: marks.__setitem__(step, time.perf_counter()))
    last = cfg["iterations"]
    return (last - warmup) / (marks[last] - marks[warmup])


def rank_main(primitives: int, size: int, views: int, steps: int, batch: int, warmup: int) -> dict:
    """One rank of the distributed configuration (started by the elastic launcher)."""
    import torch.distributed as dist

    from radfield.core.trainer import distributed

    torch.set_num_threads(1)
    world = distributed.connect(timeout=120, check_every=0)
    distributed.start_training(world, torch.device("cpu"))
    rate = _timed_train(*_setup(primitives, size, views, steps, batch), warmup, world=world)
    stats = dict(world.stats)
    per_step_bytes = stats["reduce_bytes"] // max(stats["steps"], 1)
    buffer = torch.zeros(per_step_bytes // 4)
    dist.barrier(group=world.group)
    clock = time.perf_counter()
    for _ in range(20):
        dist.all_reduce(buffer, group=world.group)
    bare = (time.perf_counter() - clock) / 20
    distributed.disconnect()
    return {"steps_per_s": rate, "reduce_ms": 1e3 * stats["reduce_seconds"] / max(stats["steps"], 1),
            "bytes": per_step_bytes, "bare_ms": 1e3 * bare}


def run_bench_dist(primitives: int = 2000, size: int = 64, views: int = 8, steps: int = 30, batch: int = 2,
                   ranks: int = 2, threads: int = 2, warmup: int = 3, echo=print) -> dict:
    from torch.distributed.launcher.api import LaunchConfig, elastic_launch

    echo(f"bench-dist: {primitives} neural primitives, {views} views of {size}x{size}, batch_views={batch}, "
         f"{steps} steps ({steps - warmup} timed); gloo on the CPU")
    saved = torch.get_num_threads()
    rates = {}
    try:
        for count in dict.fromkeys((threads, 1)):  # also 1 x 1: what each rank alone would do with the whole batch
            torch.set_num_threads(count)
            rates[count] = _timed_train(*_setup(primitives, size, views, steps, batch), warmup)
            echo(f"  1 rank  x {count} thread{'s' if count > 1 else ' '}: {rates[count]:7.2f} steps/s")
    finally:
        torch.set_num_threads(saved)
    single = rates[threads]

    config = LaunchConfig(min_nodes=1, max_nodes=1, nproc_per_node=ranks, run_id=f"bench-{uuid.uuid4().hex}",
                          rdzv_backend="c10d", rdzv_endpoint="localhost:0", max_restarts=0, monitor_interval=0.1,
                          start_method="spawn")
    old = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = str(max(1, threads // ranks))
    try:
        results = elastic_launch(config, rank_main)(primitives, size, views, steps, batch, warmup)
    finally:
        os.environ.pop("OMP_NUM_THREADS") if old is None else os.environ.__setitem__("OMP_NUM_THREADS", old)
    r0 = results[0]
    rate = min(r["steps_per_s"] for r in results.values())
    echo(f"  {ranks} ranks x {max(1, threads // ranks)} thread{'s' if threads // ranks > 1 else ''}: {rate:7.2f} "
         f"steps/s ({rate / single:.2f}x); all-reduce {r0['reduce_ms']:.2f} ms/step inside training "
         f"(with waiting for the slower rank), {r0['bare_ms']:.2f} ms bare; "
         f"{r0['bytes'] / 1e6:.3f} MB all-reduced per step")
    return {"single_steps_per_s": single, "one_thread_steps_per_s": rates[1], "ranks_steps_per_s": rate, **r0}
