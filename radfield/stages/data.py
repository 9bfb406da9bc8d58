"""Stage "data": check a dataset once, up front, and describe it for every later stage.

Outputs (in RUN/data/): `scene.json` (cameras of every split in the dataset's world frame, image
paths, background, normalisation, extent) and `points.npz` (SfM points, the dataset's mesh); their
formats, the splits and the normalisation are described in radfield.datasets.scene. A view's
conditions (radfield/conditions: its time, its light) stay in scene.json unless data.<condition>
is ignore; they choose the kind the run trains (stages/init.primitive_kind).
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

# Normalization, Scene and load_scene are re-exported for the stages that import them from here
from radfield import conditions
from radfield.datasets.scene import FORMAT_VERSION, POINTS, SCENE, Normalization, Scene, load_scene, read_dataset
from radfield.pipeline.runner import INPUT, Context, Stage
from radfield.stages.sfm import SFM_DATASET

__all__ = ["POINTS", "SCENE", "STAGE", "Normalization", "Scene", "load_scene", "run"]


def run(ctx: Context) -> dict[str, Any]:
    # photos arrive posed by the sfm stage (its COLMAP folder); other datasets are read as given
    source = ctx.inputs[SFM_DATASET] or ctx.inputs[INPUT]
    scene, points = read_dataset(source, ctx.config["data"])
    scene = conditions.without_ignored(scene, ctx.config["data"])
    # the distinct values of each condition the views carry (a dynamic scene's moments, a capture's lights)
    counts = {c.name: len(values) for c in conditions.registered() if (values := conditions.distinct(scene["splits"], c.name))}
    ctx.outputs[SCENE].write_text(json.dumps(scene, indent=1) + "\n")
    np.savez(ctx.outputs[POINTS], **points)
    splits = scene["splits"]
    first = splits["train"][0]
    ctx.log(f"{scene['format']} dataset, {len(splits['train'])} train / {len(splits['test'])} test views"
            + ("" if scene["posed"] else " (unposed: the sfm stage poses them)")
            + "".join(f", {conditions.get(name).model_words}: {n} {conditions.get(name).plural}"
                      for name, n in counts.items()))
    return {
        "images": sum(len(views) for views in splits.values()),
        "train_images": len(splits["train"]),
        "test_images": len(splits["test"]),
        "width": first["width"],
        "height": first["height"],
        "points": len(points["xyz"]),
        "format": scene["format"],
        **{conditions.get(name).plural: n for name, n in counts.items()},   # e.g. "times": a dynamic scene's moments
    }


STAGE = Stage("data", run, config_keys=("data",), inputs=(INPUT, SFM_DATASET), outputs=(SCENE, POINTS),
              version=FORMAT_VERSION)
