"""The `radfield bench-*` benchmarks: each prints figures and asserts nothing (the work is in
radfield.bench: render, train, dist, quality, startup)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield.cli.common import Device, Quiet, progress_bar, resolve_device
from radfield.errors import RadfieldError


def bench_render(
    primitives: Annotated[int, typer.Option(help="Number of primitives.")] = 10_000,
    width: Annotated[int, typer.Option(help="Image width.")] = 256,
    height: Annotated[int, typer.Option(help="Image height.")] = 256,
    views: Annotated[int, typer.Option(help="Cameras on an orbit.")] = 4,
    repeats: Annotated[int, typer.Option(help="Timed passes over the cameras.")] = 2,
    device: Device = "cpu",
    profile: Annotated[bool, typer.Option(help="Also print the torch profiler's top costs.")] = False,
    baseline: Annotated[bool, typer.Option("--baseline", help="Also time the readable torch twins (RADFIELD_KERNELS=torch) in the same run and print the speed-up.")] = False,
):
    """Renderer speed: neural primitives against 3D Gaussians.

    A benchmark, not a test: forward and forward+backward time of neural primitives (windowed, as
    the defaults train them, and hard-edged: neural-hard) and 3D Gaussians on the same cameras and
    budgets; prints ms/frame, pairs/s and the time ratio."""
    from radfield.bench.render import run_bench

    if min(primitives, width, height, views, repeats) < 1:
        raise RadfieldError("--primitives, --width, --height, --views and --repeats must be positive")
    run_bench(primitives, width, height, views, repeats, str(resolve_device(device)), profile, echo=typer.echo,
              baseline=baseline)


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
    kinds: Annotated[str, typer.Option(help="Comma-separated: neural (the windowed density of the defaults), neural-hard (the hard-edged ellipsoid, render.window=false), gaussian, and the conditioned kinds' variants (neural-dynamic, gaussian-dynamic, ...: each orbit view at its own time).")] = "neural,gaussian",
    steps: Annotated[int, typer.Option(help="Timed training steps per row (after 2 warm-up steps).")] = 5,
    device: Device = "cpu",
    quiet: Quiet = False,
    baseline: Annotated[bool, typer.Option("--baseline", help="Also time every row on the readable torch twins (RADFIELD_KERNELS=torch) in the same run and print the speed-up.")] = False,
):
    """Training speed: ms per step, split into its parts.

    A benchmark, not a test: ms per training step of the default recipe, split into render
    forward, loss, render backward, optimiser and population control, for each primitive kind,
    count and view size; also loop.train's own ms per step, the forward's pairs/s and the peak memory
    of the steps (CPU: resident set size; CUDA: allocated)."""
    from radfield.bench.render import ALL_BENCH_KINDS
    from radfield.bench.train import run_bench_train

    counts, view_sizes = _ints(primitives, "--primitives"), _ints(sizes, "--sizes")
    kind_list = tuple(k.strip() for k in kinds.split(","))
    if not kind_list or any(k not in ALL_BENCH_KINDS for k in kind_list):
        raise RadfieldError(f"--kinds must be among {', '.join(ALL_BENCH_KINDS)}, comma-separated, got {kinds!r}")
    if steps < 1:
        raise RadfieldError("--steps must be positive")
    dev = str(resolve_device(device))
    with progress_bar(quiet) as progress:
        task = progress.add_task("bench-train", total=len(counts) * len(view_sizes) * len(kind_list))
        run_bench_train(counts, view_sizes, kind_list, steps, device=dev, echo=typer.echo,
                        advance=lambda: progress.advance(task), baseline=baseline)


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
    """Data-parallel training: 1 rank against several.

    A benchmark, not a test: steps/s of loop.train with 1 rank x THREADS threads against RANKS
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


def bench_web(
    primitives: Annotated[str, typer.Option(help="Primitive counts, comma-separated.")] = "10000,100000",
    sizes: Annotated[str, typer.Option(help="View sizes WIDTHxHEIGHT, comma-separated.")] = "256x256,800x800,1280x720",
    kinds: Annotated[str, typer.Option(help="Comma-separated: neural, gaussian.")] = "neural,gaussian",
    frames: Annotated[int, typer.Option(help="Frames the page draws at each view (each waited for).")] = 5,
    python: Annotated[bool, typer.Option("--python/--no-python", help="Also time radfield's renderer on the same cameras.")] = True,
    gpu: Annotated[bool, typer.Option("--gpu", help="Let Chromium use this machine's GPU instead of its software GL.")] = False,
):
    """The browser renderer's speed: frames per second in headless Chromium.

    A benchmark, not a test: for each kind, count and view size, the page's start-up (navigation
    to its first frame) and frames per second of `radfield export -f web` in headless Chromium
    (its software GL unless --gpu), beside radfield's own renderer's frames per second on this
    machine in the same run."""
    from radfield.bench.web import run_bench_web

    counts = _ints(primitives, "--primitives")
    try:
        views = tuple(tuple(int(v) for v in size.lower().split("x")) for size in sizes.split(","))
    except ValueError:
        views = ()
    if not views or any(len(v) != 2 or min(v) < 1 for v in views):
        raise RadfieldError(f"--sizes must be WIDTHxHEIGHT pairs separated by commas, got {sizes!r}")
    kind_list = tuple(k.strip() for k in kinds.split(","))
    if not kind_list or any(k not in ("neural", "gaussian") for k in kind_list):
        raise RadfieldError(f"--kinds takes neural and gaussian, comma-separated, got {kinds!r}")
    if frames < 1:
        raise RadfieldError("--frames must be positive")
    run_bench_web(counts, kind_list, views, frames, python, gpu, echo=typer.echo)


def static_kinds() -> list[str]:
    """The registered kinds that need no view condition (time, light), from the kind registry."""
    from radfield.core import kinds

    return [name for name in kinds.names() if not kinds.get(name).conditions]


def bench_quality(
    dataset: Annotated[Path, typer.Argument(metavar="DATASET", help="Dataset folder (any format reconstruct reads).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder for runs/, bench.md, bench.json and psnr_vs_params.png (reused: finished runs are cached).")] = Path("bench-quality"),
    budgets: Annotated[str, typer.Option(help="Primitive budgets, comma-separated: a budget B starts from exactly B primitives and does not densify; 'none' = densification without a cap.")] = "500,2000,8000,none",
    kinds: Annotated[str, typer.Option(help="Primitive kinds, comma-separated: registered kinds that need no view condition (on a dataset with times or lights each trains its conditioned version).")] = "neural,gaussian",
    iterations: Annotated[Optional[int], typer.Option(help="Training iterations of every run (default: train.iterations of pipeline.yaml, 3000); the densification schedule of the defaults is scaled to it.")] = None,
    jobs: Annotated[int, typer.Option(help="Runs at a time (each with OMP_NUM_THREADS=1).")] = 2,
    sets: Annotated[Optional[list[str]], typer.Option("--set", metavar="KEY=VALUE", help="Passed to every reconstruct, e.g. --set data.downscale=4 (repeatable).")] = None,
    quiet: Quiet = False,
):
    """Neural primitives against 3D Gaussians at equal primitive budgets (the paper's protocol).

    Runs `radfield reconstruct` for every kind and budget into OUTPUT/runs/<kind>-<budget>, then
    writes the table (OUTPUT/bench.md, bench.json: held-out PSNR, train PSNR, SSIM, LPIPS,
    primitives, parameters, size, FPS, train time, the time of all stages) and the plot of PSNR
    against parameter count (OUTPUT/psnr_vs_params.png). Densification (unbudgeted runs) follows
    the defaults' schedule, scaled by ITERATIONS / train.iterations."""
    from radfield.bench.quality import PLOT, TABLE, bench_quality as run_bench, default_iterations, parse_budgets, table

    budget_list = parse_budgets(budgets)
    iterations = default_iterations() if iterations is None else iterations
    kind_list = [k.strip() for k in kinds.split(",") if k.strip()]
    unconditioned = static_kinds()
    if not kind_list or any(k not in unconditioned for k in kind_list):
        raise RadfieldError(f"--kinds takes {', '.join(unconditioned)} (registered kinds that need no view condition), got {kinds!r}")
    if iterations < 1 or jobs < 1:
        raise RadfieldError("--iterations and --jobs must be positive")
    if not dataset.is_dir():
        raise RadfieldError(f"{dataset}: no such dataset folder")
    with progress_bar(quiet) as progress:
        task = progress.add_task(f"{len(budget_list) * len(kind_list)} reconstructions", total=len(budget_list) * len(kind_list))
        rows = run_bench(dataset, output, budgets=budget_list, kinds=kind_list, iterations=iterations, sets=sets or [],
                         jobs=jobs, on_done=lambda _row: progress.advance(task))
    typer.echo(table(rows, dataset=dataset, iterations=iterations).rstrip())
    failed = [r for r in rows if "error" in r]
    if len(failed) == len(rows):
        raise RadfieldError(f"every run failed (first: {failed[0]['error']}); see {output / TABLE}")
    typer.echo(f"table {output / TABLE}, plot {output / PLOT}" + (f"; {len(failed)} runs failed" if failed else ""))


def bench_startup(
    ctx: typer.Context,
    repeats: Annotated[int, typer.Option(help="Fresh processes per command; the median is printed.")] = 5,
):
    """Start-up time of `radfield --help` and of every command's.

    A benchmark, not a test: the start-up time of `radfield --help` and of every `radfield
    <command> --help`, each the median of REPEATS fresh processes, against the 0.5 s target."""
    from radfield.bench.startup import run_bench_startup

    if repeats < 1:
        raise RadfieldError("--repeats must be positive")
    root = ctx.find_root()   # the commands the app lists (cli/main.py registers them)
    run_bench_startup(root.command.list_commands(root), repeats, echo=typer.echo)
