"""Stage "data": check a dataset once, up front, and describe it for every later stage.

Outputs (in RUN/data/): `scene.json` (cameras of every split in the dataset's world frame, image
paths, background, normalisation, extent) and `points.npz` (SfM points, the dataset's mesh); their
formats, the splits and the normalisation are described in radfield.datasets.scene. A view's
conditions (radfield/conditions: its time, its light) stay in scene.json unless data.<condition>
is ignore; they choose the kind the run trains (stages/init.primitive_kind).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

# Normalization, Scene and load_scene are re-exported for the stages that import them from here
from radfield import conditions
from radfield.datasets.scene import (FORMAT_VERSION, POINTS, SCENE, Normalization, Scene, load_scene, read_dataset,
                                     resolve_downscale)
from radfield.pipeline.runner import INPUT, Context, Stage
from radfield.pipeline.schema import DataConfig
from radfield.stages.sfm import SFM_DATASET

__all__ = ["DATA_KEYS", "POINTS", "SCENE", "STAGE", "Normalization", "Scene", "load_scene", "resolve", "run"]

# The data keys a stage that reads the images depends on: all but data.max_size, which acts only
# through data.downscale, and `resolve` writes the factor it chose there before anything is hashed.
# Hashing max_size as well would re-run data and train when it changes nothing they do (and every
# run made before it existed).
DATA_KEYS = tuple(f"data.{key.name}" for key in dataclasses.fields(DataConfig) if key.name != "max_size")


def resolve(config: dict[str, Any], input_path: Path | None, note=None) -> None:
    """An automatic data.downscale (null) becomes the factor the dataset at `input_path` needs
    (datasets.scene.resolve_downscale: 1, or what data.max_size asks, with one note line given to
    `note`, default stderr), so that RUN/config.yaml, the cache keys and scene.json hold the number.
    For photos it is the photos' own size that counts (the sfm stage's undistorted images are about
    as large)."""
    data = config["data"]
    if data["downscale"] is None and input_path is not None:
        data["downscale"] = resolve_downscale(input_path, data, note)


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


STAGE = Stage("data", run, config_keys=DATA_KEYS, inputs=(INPUT, SFM_DATASET), outputs=(SCENE, POINTS),
              version=FORMAT_VERSION, resolve=resolve)
