"""The reconstruction pipeline: every stage, in order, and the checks made before any of them runs.

Importing a stage module is light: the stages that need pycolmap, pymeshlab, pyvista, pytetwild or
fast_simplification (sfm, triangulate, envelope, tetra) import them when they run, so a posed dataset
reconstructed with --no-cage needs none of them (tests/test_imports.py; without pycolmap the
triangulate stage is not applicable and init starts from random centres).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from radfield.errors import RadfieldError
from radfield.conditions import view_conditions, without_ignored
from radfield.datasets.scene import read_dataset
from radfield.stages import bake, bind, data, envelope, evaluate, init, sfm, tetra, train, triangulate
from radfield.pipeline.runner import Stage
from radfield.util.registry import Registry

# every stage, registered in pipeline order (pipeline.yaml's `stages:` picks and orders them by name)
STAGES: Registry[Stage] = Registry("stage")
for _module in (sfm, data, triangulate, envelope, tetra, init, train, bind, bake, evaluate):
    STAGES.register(_module.STAGE.name, _module.STAGE)
del _module


def stages() -> list[Stage]:
    """The Stage declarations, in pipeline order."""
    return list(STAGES.values())


def check(config: dict[str, Any], input_path: Path) -> None:
    """Everything about the config and the dataset a user can get wrong, checked before the run
    directory is touched (the data stage checks the dataset again, when it runs)."""
    scene, points = read_dataset(input_path, config["data"])
    init.check_config(config, points, posed=scene["posed"])
    conditions = view_conditions(without_ignored(scene, config["data"])["splits"])
    try:
        init.primitive_kind(config, conditions)   # a conditioned kind on views without its condition
    except RadfieldError as e:
        raise RadfieldError(f"{input_path}: {e}") from None
    if config["eval"]["split"] not in scene["splits"]:
        raise RadfieldError(f"config key eval.split is {config['eval']['split']} but {input_path} has only the "
                            f"{', '.join(scene['splits'])} splits")

