"""Stage "bind": the trained model's binding to the editing cage, for the editor.

Inputs: the train stage's model.safetensors and the tetra stage's cage.npz. Output:
RUN/bind/model_binding.npz, `tet` (P,) and `bary` (P, 4) of every trained primitive's centre
(radfield.core.geometry.cage.write_binding; tet -1 throughout when the run has no cage). A stage of its
own so that the train stage does not depend on the cage: re-running tetra (a changed tetra.*
key) re-binds the model in a second, it does not retrain it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from radfield.core.geometry.cage import CAGE_NPZ, write_binding
from radfield.model_file import load_model
from radfield.pipeline.runner import Context, Stage
from radfield.stages.train import MODEL_FILE
from radfield import run as layout

MODEL_BINDING = layout.BINDING_FILE  # per trained primitive: its cage tet and barycentric coordinates


def run(ctx: Context) -> dict[str, Any]:
    means = load_model(ctx.inputs[MODEL_FILE], device="cpu").means.detach().numpy()
    write_binding(ctx.outputs[MODEL_BINDING], means, ctx.inputs[CAGE_NPZ])
    with np.load(ctx.outputs[MODEL_BINDING]) as binding:
        bound = int((binding["tet"] >= 0).sum())
    return {"primitives": len(means), "bound": bound}


STAGE = Stage("bind", run, inputs=(MODEL_FILE, CAGE_NPZ), outputs=(MODEL_BINDING,))
