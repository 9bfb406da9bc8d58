"""Where `radfield edit` and `radfield animate` get a field from, and how an edited run is written.

A source is a run directory (its final model, the cage that model is bound to and its binding, as
radfield.run.Run finds them, for a reconstructed or an edited run alike) or a model file with an
optional cage file.

An edited run is a run directory without stages (its layout: radfield/run.py): the run marker
(the source run's, with `edited_from` and the dataset the source trained on as `input`), the
source run's resolved config, and RUN/edit/ holding the field (radfield.edit.field.save_field),
the spec that was applied and a manifest (provenance: the source and its model's sha256; the
options and every operation's notes). `radfield render/eval/info/export` read it like any run.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from pathlib import Path
from typing import Any

import yaml

from radfield.edit.field import Field, load_field, save_field
from radfield.errors import RadfieldError
from radfield.run import EDIT_STAGE, Run, is_run_dir
from radfield.util.atomic import atomic_folder, atomic_write_text


def source_model(path: str | Path) -> Path:
    """The model file of a source: a run directory's final model (which must exist), else `path`."""
    path = Path(path)
    if not is_run_dir(path):
        return path
    model = Run(path).model
    if not model.is_file():
        raise RadfieldError(f"{path}: run directory has no trained model yet ({model} is missing)")
    return model


def load_source(path: str | Path, cage: str | Path | None = None) -> Field:
    """A run directory (its final model, cage and binding) or a model file (with an optional cage
    file) as a Field; `cage` replaces a run's own cage (and its binding is then recomputed). Also
    EditContext.load_operand, for operations that take another field."""
    path = Path(path)
    if is_run_dir(path):
        model, run = source_model(path), Run(path)
        return load_field(model, cage or run.cage, run.binding if cage is None else None)
    if path.is_dir():
        raise RadfieldError(f"{path}: not a radfield run directory")
    if not path.is_file():
        raise RadfieldError(f"{path}: no such model file or run directory")
    return load_field(path, cage)


def write_edited_run(output: Path, source: Path, edited: Field, operations: list, options: dict[str, Any],
                     started: float) -> dict[str, int]:
    """Write the edited run `output` (atomically: nothing is left of it on failure) from `edited`,
    the result of `operations` ([(name, arguments)]) on `source` with `options`; `started` is the
    time.perf_counter() at which the edit began (the manifest records the seconds until written).
    Returns the figures: operations, primitives and how many were split."""
    source = Path(source)
    from_run = Run(source) if is_run_dir(source) else None
    marker: dict[str, Any] = {"kind": "radfield-run", "input": None}
    if from_run is not None:
        marker.update(from_run.marker())
        dataset = from_run.dataset()
        marker["input"] = str(Path(dataset).resolve()) if dataset is not None else None
    marker.update({"created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "edited_from": str(source.resolve())})
    figures = {"operations": len(operations), "primitives": len(edited.prims),
               "split": sum(int(n.get("split", 0)) for n in edited.notes)}
    with atomic_folder(output, merge=True) as tmp:  # a non-empty output only with --force (cli.common.check_output)
        run = Run(tmp)
        save_field(run.edit_dir, edited)
        atomic_write_text(run.edit_spec, yaml.safe_dump(
            {"operations": [{name: args} for name, args in operations]}, sort_keys=False))
        manifest = {"done": True, "applicable": True, "seconds": time.perf_counter() - started, "figures": figures,
                    "source": str(source.resolve()), "source_model_sha256": _sha256(source_model(source)),
                    "options": options, "notes": edited.notes}
        atomic_write_text(run.manifest_file(EDIT_STAGE), json.dumps(manifest, indent=1) + "\n")
        if from_run is not None and from_run.config_file.is_file():
            shutil.copyfile(from_run.config_file, run.config_file)
        atomic_write_text(run.marker_file, json.dumps(marker, indent=2) + "\n")
    return figures


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
