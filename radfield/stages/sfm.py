"""Stage "sfm": a folder of photos -> a posed COLMAP dataset (datasets/sfm.py: pycolmap features,
matching, incremental mapping, undistortion, normalisation). It runs first and writes
RUN/sfm/colmap/, which the data stage then reads like any other dataset; on a posed dataset it is
not applicable.
"""

from __future__ import annotations

from typing import Any

from radfield.datasets import formats
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
