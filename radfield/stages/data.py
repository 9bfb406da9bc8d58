"""Stage "data": check a dataset once, up front, and describe it for every later stage.

Outputs (in RUN/data/): `scene.json` (cameras of every split in the dataset's world frame, image
paths, background, normalisation, extent) and `points.npz` (SfM points, the dataset's mesh); their
formats, the splits and the normalisation are described in radfield.datasets.scene. A view's
conditions (`CONDITIONS`: its time, its light) stay in scene.json unless data.time or data.light
is ignore; they choose the kind the run trains (stages/init.primitive_kind).
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

# Normalization, Scene and load_scene are re-exported for the stages that import them from here
from radfield.datasets.conditions import scene_lights, scene_times, without_ignored
from radfield.datasets.scene import FORMAT_VERSION, POINTS, SCENE, Normalization, Scene, load_scene, read_dataset
from radfield.pipeline.runner import INPUT, Context, Stage
from radfield.stages.sfm import SFM_DATASET

__all__ = ["POINTS", "SCENE", "STAGE", "Normalization", "Scene", "load_scene", "run"]


def run(ctx: Context) -> dict[str, Any]:
    # photos arrive posed by the sfm stage (its COLMAP folder); other datasets are read as given
    source = ctx.inputs[SFM_DATASET] or ctx.inputs[INPUT]
    scene, points = read_dataset(source, ctx.config["data"])
    scene = without_ignored(scene, ctx.config["data"])
    times, lights = scene_times(scene), scene_lights(scene)
    ctx.outputs[SCENE].write_text(json.dumps(scene, indent=1) + "\n")
    np.savez(ctx.outputs[POINTS], **points)
    splits = scene["splits"]
    first = splits["train"][0]
    ctx.log(f"{scene['format']} dataset, {len(splits['train'])} train / {len(splits['test'])} test views"
            + ("" if scene["posed"] else " (unposed: the sfm stage poses them)")
            + (f", dynamic: {len(times)} times" if times else "")
            + (f", relightable: {len(lights)} lights" if lights else ""))
    return {
        "images": sum(len(views) for views in splits.values()),
        "train_images": len(splits["train"]),
        "test_images": len(splits["test"]),
        "width": first["width"],
        "height": first["height"],
        "points": len(points["xyz"]),
        "format": scene["format"],
        **({"times": len(times)} if times else {}),   # a dynamic scene: its distinct moments
        **({"lights": len(lights)} if lights else {}),   # a one-light-at-a-time capture: its distinct lights
    }


STAGE = Stage("data", run, config_keys=("data",), inputs=(INPUT, SFM_DATASET), outputs=(SCENE, POINTS),
              version=FORMAT_VERSION)
