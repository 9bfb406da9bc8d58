"""Stage "triangulate": sparse points for a posed dataset that carries none (fern's transforms.json,
NeRF-synthetic), so that init starts from the scene's surfaces as 3DGS does, not from random
centres, and the envelope has points to wrap.

The training views' SIFT features are matched and triangulated with the dataset's own cameras held
fixed (datasets/sfm.py `triangulate`: the `sfm` settings, the run's seed), in the dataset's world
frame. Writes `triangulated.npz` (`xyz` (P, 3) float64, `rgb` (P, 3) in [0, 1]: the colours of
the features), which the init stage (`init.source` triangulate, and auto after mesh and points)
and the envelope stage (`envelope.source` triangulate) read: the triangulation runs once.

Not applicable when the dataset has points or a mesh of its own (photos get theirs from the sfm
stage), for a dynamic scene (its views show different moments: nothing stays put to triangulate),
without pycolmap (a GPU machine that trains `--no-cage`: init falls back to random centres), and
when fewer than MIN_POINTS points come out (views too small or too plain for features); the reason
says which.
"""

from __future__ import annotations

import importlib
from typing import Any

import numpy as np

from radfield import conditions
from radfield.core.geometry.envelope import MIN_POINTS
from radfield.datasets.scene import POINTS, SCENE, load_scene
from radfield.pipeline.runner import Context, NotApplicable, Stage

TRIANGULATED = "triangulated.npz"


def run(ctx: Context) -> dict[str, Any]:
    scene = load_scene(ctx.inputs[SCENE])
    with np.load(ctx.inputs[POINTS]) as points:
        if len(points["mesh_vertices"]) or len(points["xyz"]):
            own = "mesh.ply" if len(points["mesh_vertices"]) else "SfM points"
            raise NotApplicable(f"the dataset has its own {own}")
    if "time" in conditions.view_conditions(scene.splits):
        raise NotApplicable("a dynamic scene: its views show different moments, whose features do not triangulate")
    try:
        importlib.import_module("pycolmap")
    except ImportError:
        raise NotApplicable("pycolmap is not installed (pip install pycolmap): nothing to triangulate with") from None
    from radfield.datasets.sfm import triangulate  # pycolmap: only for posed photos without points

    train = scene.dataset("train")
    images = (train.load_image(k)[0].numpy() for k in range(len(train)))  # one at a time: 100 views of 800²
    xyz, rgb = triangulate(train.cameras, images, ctx.config["sfm"], seed=ctx.seed, log=ctx.log)
    if len(xyz) < MIN_POINTS:
        raise NotApplicable(f"only {len(xyz)} points triangulated from the {len(train)} posed training views "
                            f"(at least {MIN_POINTS} make a start or an envelope)")
    np.savez(ctx.outputs[TRIANGULATED], xyz=xyz, rgb=rgb)
    ctx.log(f"{len(xyz)} points triangulated from {len(train)} posed training views")
    return {"points": len(xyz), "views": len(train)}


STAGE = Stage("triangulate", run, config_keys=("sfm", "seed"), inputs=(SCENE, POINTS), outputs=(TRIANGULATED,))
