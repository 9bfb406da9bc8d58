"""Stage "eval": the trained model measured on the run's split eval.split, by the evaluation that
`radfield eval` runs too (radfield.evaluation.evaluate, whose docstring describes what is written:
metrics.json, renders/, report.md, grids/, training/ and figures/)."""

from __future__ import annotations

import json
from typing import Any

from radfield.datasets.scene import SCENE, load_scene
from radfield.evaluation.evaluate import (FIGURES, GRIDS, METRICS, RENDERS, REPORT, TRAINING, check_supersample, evaluate,
                                          write_report)
from radfield.pipeline.runner import Context, Stage
from radfield.pipeline.schema import EvalConfig
from radfield.run import Run
from radfield.stages.train import MODEL_FILE


def run(ctx: Context) -> dict[str, Any]:
    check_supersample(ctx.inputs[MODEL_FILE], ctx.config["render"]["supersample"])
    split = EvalConfig.from_dict(ctx.config["eval"]).split
    scene = load_scene(ctx.inputs[SCENE])
    metrics = evaluate(ctx.inputs[MODEL_FILE], scene, split, ctx.outputs[RENDERS],
                       near=ctx.config["render"]["near"], device=ctx.device, quiet=ctx.quiet, grids=ctx.outputs[GRIDS])
    ctx.outputs[METRICS].write_text(json.dumps(metrics, indent=1) + "\n")
    inside = Run(ctx.run_dir).trained_model.relative_to(ctx.run_dir)
    model = "/".join((ctx.run_dir.name, *inside.parts))  # the report names it RUN/train/model.safetensors
    write_report(ctx.tmp, metrics, model=model, run_dir=ctx.run_dir, cameras=scene.cameras(split))
    return {key: metrics[key] for key in ("psnr", "ssim", "lpips", "fps", "views")}


STAGE = Stage("eval", run, config_keys=("eval", "render.near", "render.supersample"), inputs=(SCENE, MODEL_FILE),
              outputs=(METRICS, RENDERS, REPORT, GRIDS, TRAINING, FIGURES), version=4)
