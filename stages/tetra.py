"""Stage "tetra": the editing cage, a coarse tet mesh of the envelope stage's `envelope.ply`
(core/cage.py: fTetWild through pytetwild). Writes `cage.vtk` and `cage.npz`; without an envelope
it is not applicable.
"""

from __future__ import annotations

from typing import Any

from radfield.core.cage import CAGE_FILES, build_cage, write_cage
from radfield.stages.config import require
from radfield.stages.envelope import ENVELOPE, read_envelope
from radfield.stages.pipeline import Context, NotApplicable, Stage


def run(ctx: Context) -> dict[str, Any]:
    if ctx.inputs[ENVELOPE] is None:
        raise NotApplicable("no envelope to fill (see the envelope stage)")
    vertices, tets, figures = build_cage(*read_envelope(ctx.inputs[ENVELOPE]), ctx.config["tetra"])
    write_cage(ctx.tmp, vertices, tets)
    ctx.log(f"{figures['tets']} tets, {figures['vertices']} vertices")
    return figures


STAGE = Stage("tetra", run, config_keys=("tetra",), inputs=(ENVELOPE,), outputs=CAGE_FILES)


def check_config(config: dict[str, Any]) -> None:
    """The `tetra` settings a user can get wrong, checked before anything runs."""
    for key in ("edge_length_fac", "epsilon"):
        require(config, f"tetra.{key}", lambda x: 0 < x < 1, "in (0, 1)")
    require(config, "tetra.num_threads", lambda n: n >= 1, "at least 1")
