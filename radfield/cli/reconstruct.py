"""`radfield reconstruct`: the cached pipeline (radfield.stages.registry's stages) on a dataset,
in one process, under torchrun, or on --nproc local ranks (radfield.core.trainer.launch)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield.cli.common import KINDS, parse_background, resolve_device


def reconstruct(
    input_path: Annotated[Path, typer.Argument(metavar="INPUT", help="Dataset folder (NeRF-synthetic, nerfstudio/instant-ngp, COLMAP) or a folder of photos (posed by SfM).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Run directory (created). Run again on it to resume or to redo only what changed.")],
    primitive: Annotated[Optional[str], typer.Option(metavar=KINDS, help="The kind of primitive: neural (splattable neural primitives, the default) or gaussian (3DGS, the baseline); a dynamic or relighting dataset trains their time- or light-conditioned variant. (config key train.primitive)")] = None,
    max_primitives: Annotated[Optional[int], typer.Option(help="Hard primitive budget, initialised exactly (the paper's memory-budget protocol). (config key train.max_primitives)")] = None,
    iterations: Annotated[Optional[int], typer.Option(help="Optimisation steps; raising it on a finished run continues from its final state (see docs/usage.md, 'Training: log, curves, continuing'). (config key train.iterations)")] = None,
    downscale: Annotated[Optional[int], typer.Option(help="Integer image downscale factor; 1 keeps the full size (default: automatic, images larger than data.max_size are downscaled to fit it). (config key data.downscale)")] = None,
    background: Annotated[Optional[str], typer.Option(help="Background colour R,G,B in [0, 1] for RGBA images and renders. (config key data.background)")] = None,
    seed: Annotated[Optional[int], typer.Option(help="Random seed. (config key seed)")] = None,
    device: Annotated[Optional[str], typer.Option(help="cpu or cuda[:N]; not part of the cache key. (config key device)")] = None,
    config: Annotated[Optional[Path], typer.Option("--config", help="YAML file overriding pipeline.yaml (a partial copy).")] = None,
    sets: Annotated[Optional[list[str]], typer.Option("--set", metavar="KEY=VALUE", help="Override one config key, e.g. --set train.iterations=500 (repeatable; wins over the flags).")] = None,
    force: Annotated[Optional[list[str]], typer.Option("--force", metavar="STAGE", help="Re-run this stage even if cached (repeatable).")] = None,
    from_stage: Annotated[Optional[str], typer.Option("--from", metavar="STAGE", help="Re-run this stage and every later one.")] = None,
    until_stage: Annotated[Optional[str], typer.Option("--until", metavar="STAGE", help="Stop after this stage.")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress output (for CI); the summary is still printed.")] = False,
    no_cage: Annotated[bool, typer.Option("--no-cage", help="Build no envelope and no editing cage (init and train run as for a dataset without geometry). (config key envelope.source=none)")] = False,
    nproc: Annotated[int, typer.Option("--nproc", min=1, help="Train data-parallel on this many local ranks, started here through torch's launcher (train.batch_views is split across them; docs/usage.md 'Distributed training'). Under torchrun leave it out.")] = 1,
):
    """Reconstruct a radiance field from a dataset and print its held-out PSNR.

    Runs the cached stages sfm → data → triangulate → envelope → tetra → init → train → bind → bake →
    eval in the run directory (sfm only for a folder of photos, triangulate only for a posed dataset
    without points); a stage re-runs only when its inputs or its config keys changed."""
    from radfield.core.trainer import distributed, launch
    from radfield.stages import data, registry
    from radfield.pipeline.config import load_config
    from radfield.pipeline.schema import typed
    from radfield.pipeline.info import conditioned_scene, run_info
    from radfield.pipeline.runner import run_pipeline

    if launch.follower():  # torchrun's ranks >= 1 only train, with what rank 0 sends them
        return launch.follow()
    flags = {"train.primitive": primitive, "train.max_primitives": max_primitives, "train.iterations": iterations,
             "data.downscale": downscale, "seed": seed, "device": device,
             "data.background": list(parse_background(background)) if background is not None else None,
             "envelope.source": "none" if no_cage else None}
    cfg = load_config(config, sets or [], {key: value for key, value in flags.items() if value is not None})
    resolve_device(cfg["device"])
    launching = nproc > 1 and not distributed.launched()
    # an automatic downscale: the factor, and its note once (by rank 0 when launching), before anything reads the images
    data.resolve(cfg, input_path, note=(lambda _line: None) if launching else None)
    settings = typed(cfg)
    registry.check(cfg, input_path)
    if launching:
        return launch.launch(nproc, cfg, output, sys.argv[1:])
    with launch.leading(cfg):  # rank 0 of torchrun's ranks (nothing for a single process)
        status = run_pipeline(registry.stages(), output, settings, input_path=input_path, force=force or [],
                              from_stage=from_stage, until_stage=until_stage, quiet=quiet,
                              log=lambda line: typer.echo(line, err=True))
    typer.echo("stages: " + ", ".join(f"{name} {outcome}" for name, outcome in status.items()))
    info = run_info(output)
    evaluation = info["stages"].get("eval", {})
    if status.get("eval") in ("ran", "cached") and "psnr" in evaluation:
        split = settings.eval.split
        what = "held-out" if split != "train" else "training-view"
        typer.echo(f"{what} PSNR {evaluation['psnr']:.2f} dB, SSIM {evaluation['ssim']:.4f} "
                   f"({evaluation['views']} {split} views); report {output / 'eval'}")
    if "kind" in info["stages"].get("init", {}):   # docs/usage.md "Dynamic scenes", "Relighting"
        for scene in conditioned_scene(info):
            typer.echo(f"{scene}, {info['stages']['init']['kind']} primitives")
    if info["model"]:
        typer.echo(f"model: {info['model']}")
