"""`radfield eval`, `radfield bake` and `radfield bench-quality`: measuring models and making the
delivery form of one. Argument handling only; the work is in radfield.stages and radfield.core."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield.cli.common import parse_background, resolve_device
from radfield.errors import RadfieldError


# options shared by eval and bake
Dataset = Annotated[Optional[Path], typer.Option("--dataset", "-d", help="Dataset with the ground truth and the cameras (default: the run's input; its SfM output for photos).")]
Downscale = Annotated[Optional[int], typer.Option(help="Image downscale factor (default: the run's, else 1).")]
Background = Annotated[Optional[str], typer.Option(help="Background R,G,B (default: the run's, else 1,1,1).")]
Device = Annotated[str, typer.Option(help="cpu or cuda.")]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")]


def _data_options(downscale: int | None, background: str | None) -> dict:
    options = {"data.downscale": downscale,
               "data.background": list(parse_background(background)) if background is not None else None}
    return {k: v for k, v in options.items() if v is not None}


def eval_command(
    targets: Annotated[list[Path], typer.Argument(metavar="RUN_OR_MODEL...", help="A run directory (its final model) or a .safetensors model file; several with --compare.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Report folder (created; entries of an existing one are replaced).")],
    compare: Annotated[bool, typer.Option("--compare", help="Evaluate every RUN_OR_MODEL on the same views: one table and side-by-side grids.")] = False,
    dataset: Dataset = None,
    split: Annotated[str, typer.Option(help="train, val or test.")] = "test",
    downscale: Downscale = None,
    background: Background = None,
    device: Device = "cpu",
    quiet: Quiet = False,
):
    """Measure a trained model on a dataset split: PSNR, SSIM, LPIPS (AlexNet v0.1), FPS.

    Writes OUTPUT/metrics.json (per view and mean), OUTPUT/report.md (the tables, model size,
    primitive and parameter counts), OUTPUT/grids/<view>.png (ground truth | render | error map),
    the renders to OUTPUT/renders/ and the run's training curves to OUTPUT/training/ when it has
    them. With --compare: OUTPUT/report.md and comparison.json compare the runs (train time from
    their manifests), OUTPUT/grids/ holds ground truth | run A | run B ..., and OUTPUT/<run>/ each
    run's own evaluation."""
    from radfield.delivery.compare import compare as compare_runs
    from radfield.stages.evaluate import eval_report

    dev = str(resolve_device(device))
    options = _data_options(downscale, background)
    if compare:
        rows = compare_runs(targets, output, dataset=dataset, split=split, options=options, device=dev, quiet=quiet)
        for row in rows:
            m = row["metrics"]
            lp = "-" if m.get("lpips") is None else f"{m['lpips']:.4f}"
            typer.echo(f"{row['label']}: PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f}, LPIPS {lp}, "
                       f"{m['num_primitives']} {m['kind']} primitives, {m['fps']:.1f} fps")
        typer.echo(f"comparison of {len(rows)} models on {rows[0]['metrics']['views']} {split} views in {output}")
        return
    if len(targets) != 1:
        raise RadfieldError(f"eval takes one RUN_OR_MODEL ({len(targets)} given); add --compare to compare several")
    metrics = eval_report(targets[0], dataset, split, output, options=options, device=dev, quiet=quiet)
    lp = f"LPIPS {metrics['lpips']:.4f}" if metrics.get("lpips") is not None else f"LPIPS n/a ({metrics.get('lpips_note')})"
    typer.echo(f"{metrics['split']}: PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}, {lp}, "
               f"{metrics['fps']:.1f} fps over {metrics['views']} views ({metrics['num_primitives']} "
               f"{metrics['kind']} primitives); report in {output / 'report.md'}")


def bake(
    target: Annotated[Path, typer.Argument(metavar="RUN_OR_MODEL", help="A run directory (its final model) or a .safetensors model file.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="The baked model file to write (.safetensors).")],
    min_weight: Annotated[Optional[float], typer.Option(help="Prune primitives whose transmittance-weighted alpha stays below this in every pixel of every training view (default: the run's bake.min_weight, else 1/255).")] = None,
    fp16: Annotated[Optional[bool], typer.Option("--fp16/--fp32", help="Store the tensors as float16 (default: the run's bake.fp16, else float32).")] = None,
    dataset: Dataset = None,
    split: Annotated[str, typer.Option(help="Held-out split for the PSNR before and after.")] = "test",
    downscale: Downscale = None,
    background: Background = None,
    device: Device = "cpu",
    quiet: Quiet = False,
):
    """Bake a model for delivery: prune primitives no training view sees, optionally float16.

    Prints the primitive count and file size before and after and the held-out PSNR change."""
    from radfield.stages.bake import bake_model, check_config
    from radfield.stages.evaluate import resolve_target

    options = _data_options(downscale, background)
    if min_weight is not None:
        options["bake.min_weight"] = min_weight
    if fp16 is not None:
        options["bake.fp16"] = fp16
    model, scene, _, config = resolve_target(target, dataset, options)
    check_config(config)
    if output.is_dir():
        raise RadfieldError(f"{output}: is a folder; give the model file to write")
    if output.resolve() == Path(model).resolve():
        raise RadfieldError(f"{output}: would overwrite the model being baked")
    f = bake_model(model, scene, output, min_weight=config["bake"]["min_weight"], fp16=config["bake"]["fp16"],
                   split=split, near=config["render"]["near"], device=str(resolve_device(device)), quiet=quiet)
    typer.echo(f"baked {f['primitives_before']} -> {f['primitives_after']} primitives ({f['pruned']} pruned), "
               f"{f['size_before']} -> {f['size_after']} bytes{' (float16)' if f['fp16'] else ''}; "
               f"{split} PSNR {f['psnr_before']:.2f} -> {f['psnr_after']:.2f} dB ({f['psnr_change']:+.3f}); wrote {output}")


def bench_quality(
    dataset: Annotated[Path, typer.Argument(metavar="DATASET", help="Dataset folder (any format reconstruct reads).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder for runs/, bench.md, bench.json and psnr_vs_params.png (reused: finished runs are cached).")] = Path("bench-quality"),
    budgets: Annotated[str, typer.Option(help="Primitive budgets, comma-separated: a budget B starts from exactly B primitives and does not densify; 'none' = densification without a cap.")] = "500,2000,8000,none",
    kinds: Annotated[str, typer.Option(help="Primitive kinds, comma-separated: neural, gaussian.")] = "neural,gaussian",
    iterations: Annotated[Optional[int], typer.Option(help="Training iterations of every run (default: train.iterations of pipeline.yaml, 3000); the densification schedule of the defaults is scaled to it.")] = None,
    jobs: Annotated[int, typer.Option(help="Runs at a time (each with OMP_NUM_THREADS=1).")] = 2,
    sets: Annotated[Optional[list[str]], typer.Option("--set", metavar="KEY=VALUE", help="Passed to every reconstruct, e.g. --set data.downscale=4 (repeatable).")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
):
    """Neural primitives against 3D Gaussians at equal primitive budgets (the paper's protocol).

    Runs `radfield reconstruct` for every kind and budget into OUTPUT/runs/<kind>-<budget>, then
    writes the table (OUTPUT/bench.md, bench.json: held-out PSNR, train PSNR, SSIM, LPIPS,
    primitives, parameters, size, FPS, train time, the time of all stages) and the plot of PSNR
    against parameter count (OUTPUT/psnr_vs_params.png). Densification (unbudgeted runs) follows
    the defaults' schedule, scaled by ITERATIONS / train.iterations."""
    from radfield.bench.quality import PLOT, TABLE, bench_quality as run_bench, default_iterations, parse_budgets, table
    from radfield.cli.common import progress_bar

    budget_list = parse_budgets(budgets)
    iterations = default_iterations() if iterations is None else iterations
    kind_list = [k.strip() for k in kinds.split(",") if k.strip()]
    if not kind_list or any(k not in ("neural", "gaussian") for k in kind_list):
        raise RadfieldError(f"--kinds takes neural and/or gaussian, got {kinds!r}")
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
