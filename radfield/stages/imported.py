"""An imported run (`radfield import MODEL -o RUN`): a model that came from elsewhere (a 3DGS PLY, SPZ,
glTF, `.splat`, an official Splat the Net PLY, a radfield model file without its run) made into a
run directory, so that edit, animate, render, eval, bake, view and export work on it as on a
trained run.

`write_import(prims, format, model_file, folder, ...)` (the model as `read_foreign` read it) writes
RUN/import/, the run's INPUT: the model converted to radfield's model file (`model.safetensors`),
and the model's own renders from an orbit about it as a NeRF-synthetic dataset
(radfield.delivery.orbit_dataset: RGBA, so the silhouettes carve a visual hull), with the model's
centres as its point cloud (`mesh.ply`, coloured by their SH's constant term: the dataset's own
points, so there is nothing to triangulate); `import.json` records where
the model came from. Then the usual stages run on that input:

    sfm (not applicable) → data → triangulate (not applicable)
        → envelope (the visual hull of the renders' alpha) → tetra → train → bind

where "train" is `STAGE` here: it trains nothing, it takes the imported model. The renders are what
every later command that needs a dataset reads: the teacher and the cameras of eval, render and
view, the training views of bake. The model's own renders are also what eval scores it against by
default (a lossless import scores above 100 dB there; `--dataset` scores it against photos).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Any

from radfield import model_formats
from radfield.core import kinds
from radfield.delivery.orbit_dataset import write_orbit_dataset
from radfield.errors import RadfieldError
from radfield.model_file import save_model
from radfield.pipeline.runner import INPUT, Context, Stage
from radfield.stages import registry
from radfield.util.progress import progress_bar
from radfield import run as layout

MODEL_FILE = layout.MODEL_FILE     # the train stage's output, as the trained runs have it
IMPORTED_MODEL = "model.safetensors"   # in RUN/import/: the model converted to radfield's file
RECORD = layout.IMPORT_RECORD      # in RUN/import/: where it came from
POINTS = "mesh.ply"                # in RUN/import/: the model's centres as the dataset's point cloud
STAGE_NAMES = ("sfm", "data", "triangulate", "envelope", "tetra", "train", "bind")   # an imported run's `stages:`


def stages() -> list[Stage]:
    """The pipeline's stages with this module's `train` in place of the trainer (STAGE_NAMES picks them)."""
    return [stage for stage in registry.stages() if stage.name != "train"] + [STAGE]


def read_foreign(model_file: Path):
    """The model in `model_file` (any format radfield reads) and its format's name; one error line
    for a conditioned kind (its renders would need a time or a light a view)."""
    fmt = model_formats.detect(model_file)
    prims = fmt.read(Path(model_file))
    if kinds.get(prims.kind).conditions:
        raise RadfieldError(f"{model_file}: a {prims.kind} model; radfield import takes static models "
                            f"(edit, render, view and export take this file directly)")
    return prims, fmt.name


def write_import(prims, fmt: str, model_file: Path, folder: Path, views: int, test_views: int, size: int,
                 quiet: bool = False) -> dict[str, Any]:
    """Write RUN/import/ (module docstring) into `folder`, which must not exist, for the model
    `prims` read from `model_file` (of format `fmt`: read_foreign); the record (import.json)."""
    folder.mkdir(parents=True)
    save_model(folder / IMPORTED_MODEL, prims)
    _write_points(prims, folder / POINTS)
    with progress_bar(quiet) as progress:
        task = progress.add_task(f"rendering {views + test_views} views of the model", total=views + test_views)
        figures = write_orbit_dataset(prims, folder, views, test_views, size, on_view=lambda: progress.advance(task))
    record = {"source": str(Path(model_file).resolve()), "format": fmt, "kind": prims.kind, "primitives": len(prims),
              "sha256": hashlib.sha256(Path(model_file).read_bytes()).hexdigest(), **figures}
    (folder / RECORD).write_text(json.dumps(record, indent=1) + "\n")
    return record


def _write_points(prims, path: Path) -> None:
    """The centres as a point cloud PLY, each coloured by its SH's constant term."""
    import meshio
    import numpy as np

    from radfield.core.splat.sh import C0

    rgb = (prims.sh[:, 0].detach().double() * C0 + 0.5).clamp(0, 1).numpy()
    colour = {name: np.rint(rgb[:, k] * 255).astype(np.uint8) for k, name in enumerate(("red", "green", "blue"))}
    meshio.write_points_cells(path, prims.means.detach().numpy().astype(np.float32), [], point_data=colour, binary=True)


def read_record(input_folder: Path) -> dict[str, Any] | None:
    """An imported run's import.json (None: not an imported run's input, or unreadable)."""
    try:
        record = json.loads((Path(input_folder) / RECORD).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def run(ctx: Context) -> dict[str, Any]:
    record = read_record(ctx.inputs[INPUT])
    if record is None:
        raise RadfieldError(f"{ctx.inputs[INPUT]}: not the input of an imported run (no {RECORD})")
    shutil.copyfile(ctx.inputs[INPUT] / IMPORTED_MODEL, ctx.outputs[MODEL_FILE])
    return {"primitives": record["primitives"], "kind": record["kind"], "imported_from": record["source"],
            "format": record["format"]}


STAGE = Stage("train", run, inputs=(INPUT,), outputs=(MODEL_FILE,))
