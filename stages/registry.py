"""The reconstruction pipeline: every stage, in order, and the checks made before any of them runs.

Stages whose module is not written yet get a stand-in, so the pipeline is complete today: the
photo front end (sfm, envelope, tetra) reports "not applicable" on a posed dataset and refuses
unposed photos; a missing train stage refuses to run. A module's own import errors propagate.
"""

from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path
from typing import Any

from radfield.core.errors import RadfieldError
from radfield.stages import data, evaluate, init
from radfield.stages.data import SCENE, load_scene
from radfield.stages.info import MODEL_FILE
from radfield.stages.pipeline import Context, NotApplicable, Stage

def stages() -> list[Stage]:
    """The Stage declarations, in pipeline order."""
    return [
        data.STAGE,
        _stage("sfm") or Stage("sfm", _photos_only("sfm"), inputs=(SCENE,)),
        _stage("envelope") or Stage("envelope", _photos_only("envelope"), inputs=(SCENE,)),
        _stage("tetra") or Stage("tetra", _photos_only("tetra"), inputs=(SCENE,)),
        init.STAGE,
        _stage("train") or Stage("train", _train_missing, inputs=(SCENE, init.INIT_MODEL), outputs=(MODEL_FILE,)),
        evaluate.STAGE,
    ]


def train_available() -> bool:
    return _stage("train") is not None


def check(config: dict[str, Any], input_path: Path) -> None:
    """Everything about the config and the dataset a user can get wrong, checked before the run
    directory is touched (the data stage checks the dataset again, when it runs)."""
    scene, points = data.read_dataset(input_path, config["data"])
    init.check_config(config, points)
    if config["eval"]["split"] not in scene["splits"]:
        raise RadfieldError(f"config key eval.split is {config['eval']['split']} but {input_path} has only the "
                            f"{', '.join(scene['splits'])} splits")


def _stage(name: str) -> Stage | None:
    """`radfield.stages.<name>.STAGE`, or None while that module or its STAGE does not exist."""
    module = f"radfield.stages.{name}"
    if importlib.util.find_spec(module) is None:
        return None
    return getattr(importlib.import_module(module), "STAGE", None)


def _photos_only(name: str):
    def run(ctx: Context) -> None:
        if load_scene(ctx.inputs[SCENE]).posed:
            raise NotApplicable("the dataset has camera poses")
        raise RadfieldError(f"unposed photos need the {name} stage, which this version of radfield does not have yet")
    return run


def _train_missing(ctx: Context) -> None:
    raise RadfieldError("the train stage is not part of this version of radfield yet")
