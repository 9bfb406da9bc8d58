"""`radfield import`: a model from elsewhere made into a run directory with a cage of its own
(radfield.stages.imported: the model's renders as the run's dataset, then the usual cage stages)."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield.cli.common import check_options, check_output, parse_background
from radfield.util.ranges import AT_LEAST_1, Range

VIEWS, TEST_VIEWS, SIZE = 56, 8, 256
IMAGE_SIZE = Range(16, 4096)


def import_model(
    model: Annotated[Path, typer.Argument(metavar="MODEL", help="A model file: a 3DGS PLY (Inria, gsplat, nerfstudio, OpenSplat, SuperSplat...), PlayCanvas compressed PLY, .splat, .spz, .glb (KHR_gaussian_splatting), an official Splat the Net PLY, or a radfield .safetensors model.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="New run directory to create (an existing non-empty folder is refused).")],
    views: Annotated[int, typer.Option(help="Views of the model rendered from an orbit about it: the run's training views (its cage's silhouettes, local retraining's teacher, bake's views).")] = VIEWS,
    test_views: Annotated[int, typer.Option(help="Further views of the orbit, the run's test split (eval, render and view's cameras).")] = TEST_VIEWS,
    size: Annotated[int, typer.Option(help="Width and height of the rendered views, in pixels.")] = SIZE,
    background: Annotated[Optional[str], typer.Option(help="Background colour R,G,B in [0, 1] the run renders over (config key data.background).")] = None,
    sets: Annotated[Optional[list[str]], typer.Option("--set", metavar="KEY=VALUE", help="Override a config key of the run, e.g. --set tetra.edge_length_fac=0.05 (repeatable).")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress output.")] = False,
):
    """Import a model that came from elsewhere as a run directory, with an editing cage built for it.

    Renders the model from an orbit about it (RGBA, RUN/import/: the run's dataset), carves the
    visual hull of those silhouettes into an envelope, fills it with a tetrahedral cage (fTetWild)
    and binds the model to it. edit, animate, render, eval (against its own renders, or
    --dataset), bake, view and export then work on RUN as on a trained run of the model's kind;
    `info` says where it came from. Static kinds only (a time- or light-conditioned radfield model is
    edited, rendered, viewed and exported as a file directly)."""
    from radfield.pipeline.config import load_config
    from radfield.pipeline.info import run_info
    from radfield.pipeline.runner import run_pipeline
    from radfield.pipeline.schema import typed
    from radfield.run import Run
    from radfield.stages import imported

    check_options({"--views": (views, AT_LEAST_1), "--test-views": (test_views, AT_LEAST_1), "--size": (size, IMAGE_SIZE)})
    check_output(output, False, folder=True)
    prims, fmt = imported.read_foreign(model)   # refused before anything is written
    options = {"stages": list(imported.STAGE_NAMES), "train.primitive": prims.kind, "envelope.source": "hull",
               "data.downscale": 1}
    if background is not None:
        options["data.background"] = list(parse_background(background))
    cfg = load_config(None, sets or [], options)
    given_empty = output.is_dir()
    run = Run(output)
    try:
        record = imported.write_import(prims, fmt, model, run.import_dir, views, test_views, size, quiet=quiet)
        run_pipeline(imported.stages(), output, typed(cfg), input_path=run.import_dir, quiet=quiet,
                     log=lambda line: typer.echo(line, err=True))
    except BaseException:
        # a half-made import is no run: nothing of it stays (an empty folder given as OUTPUT stays, empty)
        shutil.rmtree(output, ignore_errors=True)
        if given_empty:
            output.mkdir()
        raise
    info = run_info(output)
    tetra = info["stages"].get("tetra", {})
    typer.echo(f"imported {record['primitives']} {record['kind']} primitives ({record['format']}) from {model}: "
               f"{views} + {test_views} views of {size}x{size} rendered, cage of {tetra.get('tets', 0)} tets "
               f"and {tetra.get('vertices', 0)} vertices; run {output}")
