"""Stage "tetra": the editing cage, a coarse tet mesh of the envelope stage's `envelope.ply`
(core/geometry/cage.py: fTetWild through pytetwild). Writes `cage.vtk` and `cage.npz`; without an envelope
it is not applicable. When fTetWild fails, the cage is the fallback of `fallback_cage` (recorded
as `fallback` and `fallback_reason`, and printed as one warning line).
"""

from __future__ import annotations

import sys
from typing import Any

from radfield.core.geometry.cage import CAGE_FILES, build_cage, fallback_cage, tet_volumes, write_cage
from radfield.core.geometry.envelope import read_envelope
from radfield.errors import RadfieldError
from radfield.stages.envelope import ENVELOPE
from radfield.pipeline.runner import Context, NotApplicable, Stage


def run(ctx: Context) -> dict[str, Any]:
    if ctx.inputs[ENVELOPE] is None:
        raise NotApplicable("no envelope to fill (see the envelope stage)")
    envelope = read_envelope(ctx.inputs[ENVELOPE])
    try:
        vertices, tets, figures = build_cage(*envelope, ctx.config["tetra"])
        figures |= {"fallback": None, "fallback_reason": None}
    except RadfieldError as error:
        vertices, tets, name = fallback_cage(*envelope)
        figures = {"tets": len(tets), "vertices": len(vertices), "volume": float(tet_volumes(vertices, tets).sum()),
                   "fallback": name, "fallback_reason": str(error)}
        print(f"radfield: warning: tetra: fell back to a {name} cage ({error})", file=sys.stderr, flush=True)
    write_cage(ctx.tmp, vertices, tets)
    ctx.log(f"{figures['tets']} tets, {figures['vertices']} vertices")
    return figures


STAGE = Stage("tetra", run, config_keys=("tetra",), inputs=(ENVELOPE,), outputs=CAGE_FILES, version=2)
