"""The reconstruction pipeline: every stage, in order, and the checks made before any of them runs.

A missing train stage gets a stand-in that refuses to run, so the pipeline is complete while the
train module is being written. A module's own import errors propagate.
"""

from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path
from typing import Any

from radfield.errors import RadfieldError
from radfield.datasets.scene import SCENE, read_dataset
from radfield.stages import bake, bind, data, envelope, evaluate, init, sfm, tetra
from radfield.pipeline.info import MODEL_FILE
from radfield.pipeline.runner import Context, Stage


def stages() -> list[Stage]:
    """The Stage declarations, in pipeline order."""
    return [
        sfm.STAGE,
        data.STAGE,
        envelope.STAGE,
        tetra.STAGE,
        init.STAGE,
        _stage("train") or Stage("train", _train_missing, inputs=(SCENE, init.INIT_MODEL), outputs=(MODEL_FILE,)),
        bind.STAGE,
        bake.STAGE,
        evaluate.STAGE,
    ]


def train_available() -> bool:
    return _stage("train") is not None


def check(config: dict[str, Any], input_path: Path) -> None:
    """Everything about the config and the dataset a user can get wrong, checked before the run
    directory is touched (the data stage checks the dataset again, when it runs)."""
    scene, points = read_dataset(input_path, config["data"])
    for module in (sfm, envelope, tetra, bake):
        module.check_config(config)
    init.check_config(config, points, posed=scene["posed"])
    if config["eval"]["split"] not in scene["splits"]:
        raise RadfieldError(f"config key eval.split is {config['eval']['split']} but {input_path} has only the "
                            f"{', '.join(scene['splits'])} splits")


def _stage(name: str) -> Stage | None:
    """`radfield.stages.<name>.STAGE`, or None while that module or its STAGE does not exist."""
    module = f"radfield.stages.{name}"
    if importlib.util.find_spec(module) is None:
        return None
    return getattr(importlib.import_module(module), "STAGE", None)


def _train_missing(ctx: Context) -> None:
    raise RadfieldError("the train stage is not part of this version of radfield yet")
