"""What a run directory holds, for `radfield info RUN [--json]`.

The JSON of `run_info` is a stable interface (scripts and docs/formats.md rely on it)::

    {
      "run": "/abs/path/RUN",
      "input": "/abs/path/DATASET" | null,       # the INPUT the run was made from
      "model": "/abs/path/RUN/train/model.safetensors" | null,   # the final model, once trained
      "normalization": "/abs/path/RUN/sfm/colmap/normalization.json" | null,  # runs made from photos:
                                                  # x = scale * (x_sfm - center) maps COLMAP's frame to the
                                                  # run's (the frame of every artifact and model)
      "pending_checkpoint": {                     # an interrupted training run (else null): the checkpoint
        "stage": "train", "step": 1500,           #   it resumes from, the step it reached and the steps asked
        "iterations": 3000, "path": "/abs/..."    #   for (the run's config; null if unreadable)
      } | null,
      "imported_from": {                          # an imported run (`radfield import`; an edit of one
        "source": "/abs/path/MODEL.ply",          #   answers for it), else null: the model file, its
        "format": "ply-3dgs", "kind": "gaussian", #   format, kind and primitive count, its sha256, and
        "primitives": 1000, "sha256": "...",      #   the orbit rendered as the run's dataset (views,
        "views": 56, "test_views": 8, "size": 256, #  test_views, size, centre, radius)
        "centre": [0, 0, 0], "radius": 1.0
      } | null,
      "edited_from": "/abs/path/SOURCE" | null,   # an edited run (`radfield edit`): the run directory
                                                  # or model file it was made from; else null
      "edit": {                                   # an edited run (else null): when it was written, the
        "created": "2026-01-01T12:00:00+0000",    #   operations applied (its edit/spec.yaml) and that file
        "operations": [{"<name>": {...}}, ...],
        "spec": "/abs/path/RUN/edit/spec.yaml"
      } | null,
      "artifacts": {                              # what each finished stage wrote, files and folders
        "<stage>": ["/abs/path/RUN/<stage>/<output>", ...]     # (its manifest's outputs), in pipeline order
      },
      "stages": {                                 # in pipeline order; an edited run has only "edit" (the
                                                  # reconstruction's stages ran in its source run)
        "<stage>": {
          "done": true | false,                   # finished (its manifest exists)
          "seconds": 12.3 | null,                 # wall time of its last run; null if never run
          "applicable": true | false | null,      # false: nothing to do for this input; null: never run
          "reason": "...",                        # only when applicable is false
          ...figures                              # the stage's own key figures, e.g.
        }                                         #   sfm: registered_images, total_images, points,
      }                                           #   reprojection_error; data: images, times (dynamic),
    }                                             #   lights (one light at a time); envelope: faces;
                                                  #   tetra: tets, vertices; init: kind (a conditioned
                                                  #   kind the views chose); train: primitives, params,
                                                  #   iterations, train_psnr, supersample, window

Keys are only ever added, never renamed or removed. A stage shown as done may be stale if the
config changed since (`radfield reconstruct` on the run brings it up to date).
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import yaml
from rich.console import Console
from rich.table import Table

from radfield.errors import RadfieldError
from radfield.util.yamlfile import parse_yaml
from radfield.pipeline.runner import RESERVED_FIGURES, format_figures
from radfield.run import MODEL_STAGE, Run


def run_info(run_dir: Path) -> dict[str, Any]:
    """The documented JSON summary of a run directory (see the module docstring)."""
    run = Run.open(run_dir)
    stages: dict[str, Any] = {}
    artifacts: dict[str, list[str]] = {}
    for name in run.stage_names():
        manifest = run.manifest(name)
        if manifest is None:
            stages[name] = {"done": False, "seconds": None, "applicable": None}
            continue
        written = [run.stage_dir(name) / output for output in manifest.get("outputs") or {}]
        if written:
            artifacts[name] = [str(path.resolve()) for path in written if path.exists()]
        entry: dict[str, Any] = {
            "done": True,
            "seconds": manifest.get("seconds"),
            "applicable": manifest.get("applicable"),
        }
        if not manifest.get("applicable"):
            entry["reason"] = manifest.get("reason")
        entry.update(manifest.get("figures") or {})
        stages[name] = entry
    model, normalization = run.model, run.normalization
    return {
        "run": str(run.path.resolve()),
        "input": run.marker().get("input"),
        "model": str(model.resolve()) if model.is_file() else None,
        "normalization": str(normalization.resolve()) if normalization.is_file() else None,
        "pending_checkpoint": pending_checkpoint(run),
        "stages": stages,
        "imported_from": run.imported_from(),
        "edited_from": str(run.edited_from) if run.edited_from is not None else None,
        "edit": edit_info(run),
        "artifacts": artifacts,
    }


def edit_info(run: Run) -> dict[str, Any] | None:
    """What `radfield edit` made an edited run with (see the module docstring), or None."""
    if not run.is_edited:
        return None
    operations = None
    try:
        operations = (parse_yaml(run.edit_spec.read_text(encoding="utf-8")) or {}).get("operations")
    except (OSError, yaml.YAMLError, AttributeError):
        pass  # unreadable: shown as unknown
    return {"created": run.marker().get("created"), "operations": operations,
            "spec": str(run.edit_spec.resolve()) if run.edit_spec.is_file() else None}


def pending_checkpoint(run: Run) -> dict[str, Any] | None:
    """The checkpoint an interrupted training left in RUN/train.work/ (see the module docstring), or None."""
    from radfield.core.trainer.loop import checkpoint_header  # torch: only when there is a checkpoint

    path = run.checkpoint
    if not path.is_file():
        return None
    try:
        step = checkpoint_header(path)["step"]
    except (RadfieldError, KeyError):
        step = None  # damaged: the train stage reports it when it resumes
    iterations = None
    try:
        iterations = parse_yaml(run.config_file.read_text(encoding="utf-8"))["train"]["iterations"]
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        pass
    return {"stage": MODEL_STAGE, "step": step, "iterations": iterations, "path": str(path.resolve())}


def format_info(info: dict[str, Any]) -> str:
    """`run_info` as a readable table (plain text, no colour codes)."""
    table = Table(title=f"run {info['run']}", title_justify="left")
    table.add_column("stage")
    table.add_column("status")
    table.add_column("time", justify="right")
    table.add_column("figures")
    for name, entry in info["stages"].items():
        figures = {k: v for k, v in entry.items() if k not in RESERVED_FIGURES}
        table.add_row(name, _status(entry), _seconds(entry["seconds"]), format_figures(figures))
    buffer = io.StringIO()
    console = Console(file=buffer, width=110, no_color=True, highlight=False)
    console.print(table)
    console.print(f"input: {info['input'] or '-'}")
    console.print(f"model: {info['model'] or '- (not trained yet)'}")
    for scene in conditioned_scene(info):   # the kind the views' conditions chose is the init stage's
        kind = info["stages"].get("init", {}).get("kind", "not initialised yet")
        console.print(f"{scene}, primitive kind {kind}")
    pending = info.get("pending_checkpoint")
    if pending:
        of = f" of {pending['iterations']}" if pending["iterations"] is not None else ""
        step = pending["step"] if pending["step"] is not None else "? (unreadable)"
        console.print(f"pending checkpoint: {pending['stage']} interrupted at step {step}{of}; "
                      f"`radfield reconstruct` on the run resumes it ({pending['path']})")
    imported = info.get("imported_from")
    if imported:
        console.print(f"imported from: {imported.get('source')} ({imported.get('format')}, {imported.get('primitives')} "
                      f"{imported.get('kind')} primitives; its dataset: {imported.get('views')} + {imported.get('test_views')} "
                      f"views of it, {imported.get('size')} px)", soft_wrap=True)
    if info.get("edited_from"):
        console.print(f"edited from: {info['edited_from']}")
    edit = info.get("edit")
    if edit:
        operations = edit["operations"]
        count = len(operations) if isinstance(operations, list) else "? (unreadable spec)"
        console.print(f"edit: {count} operation(s), written {edit['created'] or '?'} from {edit['spec'] or '-'}", soft_wrap=True)
        for i, op in enumerate(operations if isinstance(operations, list) else [], 1):
            console.print(f"  {i}. {_operation(op)}", soft_wrap=True)
    if info["normalization"]:
        console.print(f"normalization (photos -> run frame): {info['normalization']}")
    if info.get("artifacts"):
        console.print(f"artifacts (in {info['run']}):")
        for stage, paths in info["artifacts"].items():
            console.print(f"  {stage}/: {', '.join(Path(path).name for path in paths)}", soft_wrap=True)
    return buffer.getvalue()


def conditioned_scene(info: dict[str, Any]) -> list[str]:
    """What the views carry, from the data stage's figure per condition (stages/data.py), e.g.
    ["dynamic scene: 3 moments"] or ["relightable scene: 240 lights"] ([] for a static scene under
    fixed lighting, or one whose conditions the run ignored)."""
    from radfield import conditions

    data = info["stages"].get("data", {})
    return [f"{c.model_words} scene: {data[c.plural]} {c.unit}" for c in conditions.registered() if data.get(c.plural)]


def _operation(op: Any) -> str:
    """One spec entry ({name: arguments}) on one line, e.g. `twist {axis: z, degrees_per_unit: 20}`."""
    if isinstance(op, dict) and len(op) == 1:
        (name, args), = op.items()
        return f"{name} {yaml.safe_dump(args, default_flow_style=True, width=10**6).strip()}"
    return str(op)


def _status(entry: dict[str, Any]) -> str:
    if not entry["done"]:
        return "not run"
    if entry["applicable"] is False:
        return f"n/a: {entry.get('reason')}"
    return "done"


def _seconds(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    return f"{seconds:.1f} s" if seconds < 120 else f"{seconds / 60:.1f} min"
