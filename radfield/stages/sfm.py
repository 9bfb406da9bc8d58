"""Stage "sfm": a folder of photos -> a posed COLMAP dataset (datasets/sfm.py: pycolmap features,
matching, incremental mapping, undistortion, normalisation). It runs first and writes
RUN/sfm/colmap/, which the data stage then reads like any other dataset; on a posed dataset it is
not applicable.
"""

from __future__ import annotations

from typing import Any

from radfield.datasets.readers import detect_format, photo_folder, pose_source
from radfield.datasets.sfm import run_sfm
from radfield.pipeline.config import require
from radfield.pipeline.info import SFM_DATASET
from radfield.pipeline.runner import INPUT, Context, NotApplicable, Stage


def run(ctx: Context) -> dict[str, Any]:
    source = ctx.inputs[INPUT]
    fmt = detect_format(source)
    if fmt != "images":
        raise NotApplicable(f"posed dataset: poses come from {pose_source(source, fmt)}")
    figures = run_sfm(photo_folder(source), ctx.outputs[SFM_DATASET], ctx.config["sfm"], seed=ctx.seed, log=ctx.log)
    ctx.log(f"{figures['registered_images']}/{figures['total_images']} photos registered, {figures['points']} points, "
            f"reprojection error {figures['reprojection_error']:.2f} px")
    return figures


STAGE = Stage("sfm", run, config_keys=("sfm", "seed"), inputs=(INPUT,), outputs=(SFM_DATASET,))


def check_config(config: dict[str, Any]) -> None:
    """The `sfm` settings a user can get wrong, checked before anything runs."""
    require(config, "sfm.num_threads", lambda n: n == -1 or n >= 1, "-1 (all cores) or at least 1")
    for key in ("max_image_size", "max_num_features", "exhaustive_max_images", "sequential_overlap"):
        require(config, f"sfm.{key}", lambda n: n >= 1, "at least 1")
    require(config, "sfm.min_registered_fraction", lambda x: 0 < x <= 1, "in (0, 1]")
    require(config, "sfm.target_radius", lambda x: x > 0, "positive")
