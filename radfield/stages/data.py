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


# What a view may carry besides its camera (a scene.json VIEW key each), and so condition the kind
# the run trains (stages/init.primitive_kind), with that kind in words (for messages). A new one
# also gets its config key data.<condition>: auto | ignore (pipeline.yaml, pipeline/config.CHOICES)
CONDITIONS = {"time": "time-conditioned", "light": "relightable"}


def view_conditions(splits: dict[str, list[dict[str, Any]]]) -> tuple[str, ...]:
    """The conditions (CONDITIONS order) that the views of scene.json's splits carry."""
    return tuple(c for c in CONDITIONS if any(c in view for views in splits.values() for view in views))


def without_ignored(scene: dict[str, Any], data_config: dict[str, Any]) -> dict[str, Any]:
    """The scene.json content without the conditions whose data.<condition> is ignore (the
    light-blind or time-blind baselines of issues 29 and 30: a static kind trains on the views)."""
    ignored = {c for c in CONDITIONS if data_config.get(c) == "ignore"}
    if not ignored:
        return scene
    splits = {name: [{k: v for k, v in view.items() if k not in ignored} for view in views]
              for name, views in scene["splits"].items()}
    return {**scene, "splits": splits}


def scene_times(scene: dict[str, Any]) -> list[float]:
    """The distinct times of a scene.json's views, ascending ([] for a static scene)."""
    return sorted({view["time"] for views in scene["splits"].values() for view in views if "time" in view})


def scene_lights(scene: dict[str, Any]) -> list[str]:
    """The distinct lights of a scene.json's views, as JSON text ([] under fixed lighting)."""
    return sorted({json.dumps(view["light"], sort_keys=True) for views in scene["splits"].values()
                   for view in views if "light" in view})


STAGE = Stage("data", run, config_keys=("data",), inputs=(INPUT, SFM_DATASET), outputs=(SCENE, POINTS),
              version=FORMAT_VERSION)
