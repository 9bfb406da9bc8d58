"""`radfield bench-dist`: steps/s of data-parallel training, one rank against several (bench/dist.py)."""

from __future__ import annotations

from typing import Annotated

import typer

from radfield.errors import RadfieldError


def bench_dist(
    primitives: Annotated[int, typer.Option(help="Neural primitives of the scene.")] = 2000,
    size: Annotated[int, typer.Option(help="Square view size in pixels.")] = 64,
    views: Annotated[int, typer.Option(help="Orbit views to train on.")] = 8,
    steps: Annotated[int, typer.Option(help="Training steps per configuration (the first --warmup are not timed).")] = 30,
    warmup: Annotated[int, typer.Option(help="Untimed first steps.")] = 3,
    batch: Annotated[int, typer.Option(help="train.batch_views: views per step, split across the ranks.")] = 2,
    ranks: Annotated[int, typer.Option(help="Ranks of the distributed configuration (gloo, local).")] = 2,
    threads: Annotated[int, typer.Option(help="Threads of the single rank; each of the ranks gets threads/ranks.")] = 2,
):
    """Benchmark (not a test): steps/s of trainer.train with 1 rank x THREADS threads against RANKS
    ranks x THREADS/RANKS threads on the same scene (torch.distributed, gloo), the all-reduce time
    per step and the all-reduced bytes per step."""
    from radfield.bench.dist import run_bench_dist

    if min(primitives, size, views, batch, ranks, threads) < 1 or ranks < 2:
        raise RadfieldError("--primitives, --size, --views, --batch and --threads must be positive, --ranks at least 2")
    if ranks > batch:
        raise RadfieldError(f"--batch ({batch}) must be at least --ranks ({ranks}): each rank renders a share of a step's views")
    if not 0 < warmup < steps:
        raise RadfieldError("--warmup must be positive and below --steps")
    run_bench_dist(primitives, size, views, steps, batch, ranks, threads, warmup, echo=typer.echo)
