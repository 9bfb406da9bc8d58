"""`radfield eval`: a model or a run measured on a dataset split, or several compared
(radfield.stages.evaluate, radfield.evaluation.compare)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from radfield import conditions

from radfield.cli.common import Background, Dataset, Device, Downscale, Force, Quiet, check_output, data_options, resolve_device
from radfield.errors import RadfieldError


def eval_command(
    targets: Annotated[list[Path], typer.Argument(metavar="RUN_OR_MODEL", help="A run directory (its final model) or a model file (radfield's .safetensors, or any format `radfield import` reads); several with --compare.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Report folder (created; an existing non-empty one needs --force, and then its entries of the same names are replaced).")],
    compare: Annotated[bool, typer.Option("--compare", help="Evaluate every RUN_OR_MODEL on the same views: one table and side-by-side grids.")] = False,
    dataset: Dataset = None,
    split: Annotated[str, typer.Option(help="train, val or test.")] = "test",
    downscale: Downscale = None,
    background: Background = None,
    device: Device = "cpu",
    quiet: Quiet = False,
    force: Force = False,
):
    """Measure a trained model on a dataset split: PSNR, SSIM, LPIPS (AlexNet v0.1), FPS.

    Writes OUTPUT/metrics.json (per view and mean), OUTPUT/report.md (the tables, model size,
    primitive and parameter counts), OUTPUT/grids/<view>.png (ground truth | render | error map),
    the renders to OUTPUT/renders/ and the run's training curves to OUTPUT/training/ when it has
    them. With --compare: OUTPUT/report.md and comparison.json compare the runs (train time from
    their manifests), OUTPUT/grids/ holds ground truth | run A | run B ..., and OUTPUT/<run>/ each
    run's own evaluation."""
    from radfield.evaluation.compare import compare as compare_runs
    from radfield.evaluation.evaluate import eval_report

    check_output(output, force, folder=True)
    dev = str(resolve_device(device))
    options = data_options(downscale, background)
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
    for condition in conditions.registered():   # the spread over a condition's values (the report's section)
        rows = metrics.get(f"per_{condition.name}")
        if rows:
            worst, best = min(rows, key=lambda row: row["psnr"]), max(rows, key=lambda row: row["psnr"])
            label = lambda row: f"{condition.name} {condition.label(condition.from_row(row))}"
            typer.echo(f"{len(rows)} {condition.unit}: PSNR from {worst['psnr']:.2f} dB ({label(worst)}) "
                       f"to {best['psnr']:.2f} dB ({label(best)})")
