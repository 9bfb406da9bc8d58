"""Stage "sfm": a folder of photos -> a posed COLMAP dataset (datasets/sfm.py: pycolmap features,
matching, incremental mapping, undistortion, normalisation). It runs first and writes
RUN/sfm/colmap/, which the data stage then reads like any other dataset; on a posed dataset it is
not applicable.
"""

from __future__ import annotations

from typing import Any

from radfield.datasets import formats
from radfield.pipeline.config import require
from radfield.pipeline.runner import INPUT, Context, NotApplicable, Stage
from radfield import run as layout

SFM_DATASET = layout.SFM_DATASET  # the posed COLMAP dataset folder, RUN/sfm/colmap/ (radfield.run.Run.sfm_dataset)


def run(ctx: Context) -> dict[str, Any]:
    source = ctx.inputs[INPUT]
    fmt = formats.detect(source)
    if fmt.posed:
        raise NotApplicable(f"posed dataset: poses come from {fmt.pose_source(source)}")
    from radfield.datasets.sfm import run_sfm  # pycolmap and OpenImageIO: only when photos are posed

    figures = run_sfm(fmt.photo_folder(source), ctx.outputs[SFM_DATASET], ctx.config["sfm"], seed=ctx.seed, log=ctx.log)
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
