"""What a run directory holds, for `radfield info RUN [--json]`.

The JSON of `run_info` is a stable interface (scripts and the README rely on it)::

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
from radfield.pipeline.runner import (
    CONFIG_FILE,
    MANIFEST,
    RESERVED_FIGURES,
    format_figures,
    is_run_dir,
    read_manifest,
    read_marker,
)

MODEL_STAGE = "train"  # the stage that writes the final model
MODEL_FILE = "model.safetensors"  # its file name inside RUN/train/ (the train stage's output)
CHECKPOINT_FILE = "checkpoint.safetensors"  # the train stage's checkpoint inside RUN/train.work/
SFM_STAGE = "sfm"  # the stage that poses a folder of photos
SFM_DATASET = "colmap"  # its output: a posed COLMAP dataset folder inside RUN/sfm/
NORMALIZATION_FILE = "normalization.json"  # inside that folder (datasets/sfm.py writes it; not imported
                                          # from there: radfield.datasets loads OpenImageIO, cv2, pycolmap)


EDIT_STAGE = "edit"  # `radfield edit` writes an edited run's model into NEW_RUN/edit/ (radfield.edit.field)


def model_path(run_dir: Path) -> Path:
    """Where the final model of a run lives (whether or not it exists yet): an edited run's
    edit/model.safetensors, else the train stage's."""
    edited = Path(run_dir) / EDIT_STAGE / MODEL_FILE
    return edited if edited.is_file() else Path(run_dir) / MODEL_STAGE / MODEL_FILE


def normalization_path(run_dir: Path) -> Path:
    """Where the SfM normalisation of a run made from photos lives (whether or not it exists)."""
    return Path(run_dir) / SFM_STAGE / SFM_DATASET / NORMALIZATION_FILE


def run_dataset(run_dir: Path) -> Path | None:
    """The posed dataset a run trained on: the SfM output for photos, else the run's input."""
    posed = Path(run_dir) / SFM_STAGE / SFM_DATASET
    if posed.is_dir():
        return posed
    source = read_marker(run_dir).get("input")
    return None if source is None else Path(source)


def run_info(run_dir: Path) -> dict[str, Any]:
    """The documented JSON summary of a run directory (see the module docstring)."""
    run_dir = Path(run_dir)
    if not is_run_dir(run_dir):
        raise RadfieldError(f"{run_dir} is not a radfield run directory")
    stages: dict[str, Any] = {}
    for name in _stage_names(run_dir):
        manifest = read_manifest(run_dir / name)
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
    model, normalization = model_path(run_dir), normalization_path(run_dir)
    return {
        "run": str(run_dir.resolve()),
        "input": read_marker(run_dir).get("input"),
        "model": str(model.resolve()) if model.is_file() else None,
        "normalization": str(normalization.resolve()) if normalization.is_file() else None,
        "pending_checkpoint": pending_checkpoint(run_dir),
        "stages": stages,
    }


def pending_checkpoint(run_dir: Path) -> dict[str, Any] | None:
    """The checkpoint an interrupted training left in RUN/train.work/ (see the module docstring), or None."""
    from radfield.core.train.trainer import checkpoint_header  # torch: only when there is a checkpoint

    path = Path(run_dir) / f"{MODEL_STAGE}.work" / CHECKPOINT_FILE
    if not path.is_file():
        return None
    try:
        step = checkpoint_header(path)["step"]
    except (RadfieldError, KeyError):
        step = None  # damaged: the train stage reports it when it resumes
    iterations = None
    try:
        iterations = parse_yaml((Path(run_dir) / CONFIG_FILE).read_text(encoding="utf-8"))["train"]["iterations"]
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


def _stage_names(run_dir: Path) -> list[str]:
    """Stages in the order of the run's config, then any other stage directory with a manifest."""
    names: list[str] = []
    try:
        config = parse_yaml((run_dir / CONFIG_FILE).read_text(encoding="utf-8"))
        names = [str(name) for name in config.get("stages", [])]
    except (OSError, yaml.YAMLError, AttributeError):
        pass  # no readable config: fall back to what is on disk
    extra = sorted(p.parent.name for p in run_dir.glob(f"*/{MANIFEST}") if p.parent.name not in names)
    return names + extra


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
