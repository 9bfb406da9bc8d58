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
      "stages": {                                 # in pipeline order
        "<stage>": {
          "done": true | false,                   # finished (its manifest exists)
          "seconds": 12.3 | null,                 # wall time of its last run; null if never run
          "applicable": true | false | null,      # false: nothing to do for this input; null: never run
          "reason": "...",                        # only when applicable is false
          ...figures                              # the stage's own key figures, e.g.
        }                                         #   sfm: registered_images, total_images, points,
      }                                           #   reprojection_error; data: images; envelope: faces;
    }                                             #   tetra: tets, vertices; train: primitives, params,
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
from radfield.pipeline.config import parse_yaml
from radfield.pipeline.runner import RESERVED_FIGURES, format_figures
from radfield.run import MODEL_STAGE, Run


def run_info(run_dir: Path) -> dict[str, Any]:
    """The documented JSON summary of a run directory (see the module docstring)."""
    run = Run.open(run_dir)
    stages: dict[str, Any] = {}
    for name in run.stage_names():
        manifest = run.manifest(name)
        if manifest is None:
            stages[name] = {"done": False, "seconds": None, "applicable": None}
            continue
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
    }


def pending_checkpoint(run: Run) -> dict[str, Any] | None:
    """The checkpoint an interrupted training left in RUN/train.work/ (see the module docstring), or None."""
    from radfield.core.train.trainer import checkpoint_header  # torch: only when there is a checkpoint

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
    pending = info.get("pending_checkpoint")
    if pending:
        of = f" of {pending['iterations']}" if pending["iterations"] is not None else ""
        step = pending["step"] if pending["step"] is not None else "? (unreadable)"
        console.print(f"pending checkpoint: {pending['stage']} interrupted at step {step}{of}; "
                      f"`radfield reconstruct` on the run resumes it ({pending['path']})")
    if info["normalization"]:
        console.print(f"normalization (photos -> run frame): {info['normalization']}")
    return buffer.getvalue()


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
