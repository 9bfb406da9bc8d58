"""`radfield bake`: the delivery form of a model (radfield.stages.bake)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield.cli.common import Background, Dataset, Device, Downscale, Force, Quiet, check_output, data_options, resolve_device
from radfield.errors import RadfieldError


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
    force: Force = False,
):
    """Bake a model for delivery: prune primitives no training view sees, optionally float16.

    Prints the primitive count and file size before and after and the held-out PSNR change."""
    from radfield.stages.bake import bake_model
    from radfield.evaluation.evaluate import resolve_target
    from radfield.pipeline.schema import typed

    check_output(output, force, folder=False)
    options = data_options(downscale, background)
    if min_weight is not None:
        options["bake.min_weight"] = min_weight
    if fp16 is not None:
        options["bake.fp16"] = fp16
    model, scene, _, config = resolve_target(target, dataset, options)
    if output.resolve() == Path(model).resolve():
        raise RadfieldError(f"{output}: would overwrite the model being baked")
    settings = typed(config)
    f = bake_model(model, scene, output, min_weight=settings.bake.min_weight, fp16=settings.bake.fp16,
                   split=split, near=settings.render.near, device=str(resolve_device(device)), quiet=quiet)
    typer.echo(f"baked {f['primitives_before']} -> {f['primitives_after']} primitives ({f['pruned']} pruned), "
               f"{f['size_before']} -> {f['size_after']} bytes{' (float16)' if f['fp16'] else ''}; "
               f"{split} PSNR {f['psnr_before']:.2f} -> {f['psnr_after']:.2f} dB ({f['psnr_change']:+.3f}); wrote {output}")
