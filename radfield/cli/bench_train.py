"""`radfield bench-train`: ms per training step, split into its parts (bench/train.py)."""

from __future__ import annotations

from typing import Annotated

import typer

from radfield.cli.common import progress_bar, resolve_device
from radfield.errors import RadfieldError


def _ints(text: str, option: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        values = ()
    if not values or min(values) < 1:
        raise RadfieldError(f"{option} must be positive integers separated by commas, got {text!r}")
    return values


def bench_train(
    primitives: Annotated[str, typer.Option(help="Primitive counts, comma-separated (each row keeps its count fixed).")] = "2000,10000,20000",
    sizes: Annotated[str, typer.Option(help="Square view sizes in pixels, comma-separated.")] = "64,256",
    kinds: Annotated[str, typer.Option(help="Comma-separated: neural (the windowed density of the defaults), neural-hard (the hard-edged ellipsoid, render.window=false), gaussian.")] = "neural,gaussian",
    steps: Annotated[int, typer.Option(help="Timed training steps per row (after 2 warm-up steps).")] = 5,
    device: Annotated[str, typer.Option(help="cpu or cuda.")] = "cpu",
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
    baseline: Annotated[bool, typer.Option("--baseline", help="Also time every row on the readable torch twins (RADFIELD_KERNELS=torch) in the same run and print the speed-up.")] = False,
):
    """Benchmark (not a test): ms per training step of the default recipe, split into render
    forward, loss, render backward, optimiser and population control, for each primitive kind,
    count and view size; also trainer.train's own ms per step and the forward's pairs/s."""
    from radfield.bench.render import BENCH_KINDS
    from radfield.bench.train import run_bench_train

    counts, view_sizes = _ints(primitives, "--primitives"), _ints(sizes, "--sizes")
    kind_list = tuple(k.strip() for k in kinds.split(","))
    if not kind_list or any(k not in BENCH_KINDS for k in kind_list):
        raise RadfieldError(f"--kinds must be among {', '.join(BENCH_KINDS)}, comma-separated, got {kinds!r}")
    if steps < 1:
        raise RadfieldError("--steps must be positive")
    dev = str(resolve_device(device))
    with progress_bar(quiet) as progress:
        task = progress.add_task("bench-train", total=len(counts) * len(view_sizes) * len(kind_list))
        run_bench_train(counts, view_sizes, kind_list, steps, device=dev, echo=typer.echo,
                        advance=lambda: progress.advance(task), baseline=baseline)
