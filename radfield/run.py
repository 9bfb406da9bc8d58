"""A run directory's layout, in one place: every path into a run is built here.

    RUN/radfield-run.json        marks a radfield run: the INPUT dataset it was made from, when it was
                                 created, and for an edited run the run or model it was edited from
    RUN/config.yaml              the resolved config of the latest invocation
    RUN/hashes.json              file hashes cached by (size, mtime_ns), so re-runs need not re-read data
    RUN/.lock                    held by the one invocation writing into the run
    RUN/<stage>/                 the outputs of the last successful run of a stage, and its manifest.json
    RUN/<stage>.tmp-XXXX/        outputs being written: never trusted, removed by the next invocation
    RUN/<stage>.old-XXXX/        a stage's previous outputs while the new ones are swapped in
    RUN/<stage>.work/            scratch that survives failures (checkpoints); removed on success

A stage module names its own outputs (its Stage.outputs). What commands read from a run is a
handful of products, and where each lives is known here only:

    sfm/colmap/                  the posed COLMAP dataset of a folder of photos (stage sfm), with
    sfm/colmap/normalization.json  the similarity from COLMAP's frame to the run's
    data/scene.json              the dataset described for every later stage (stage data)
    envelope/envelope.ply        the closed surface around the object (stage envelope)
    tetra/cage.npz               the editing cage (stage tetra; cage.vtk beside it)
    train/model.safetensors      the trained model (stage train); train.work/checkpoint.safetensors
                                 the checkpoint of an interrupted training
    bind/model_binding.npz       the trained primitives' tets and barycentric coordinates in the cage
    eval/metrics.json            the held-out metrics (stage eval; a stable interface)
    import/                      an imported run's INPUT (`radfield import`): the model converted
                                 (model.safetensors), its renders from an orbit as a NeRF-synthetic
                                 dataset, the model's centres (mesh.ply), and import.json: where
                                 it came from (stages/imported.py writes it)
    edit/                        an edited run (`radfield edit`): model.safetensors, cage.npz (+ .vtk),
                                 model_binding.npz, spec.yaml and manifest.json, instead of the stages

The file names are defined here and the writers import them (a stage module, core/geometry/cage.py,
edit/field.py, datasets/sfm.py, datasets/scene.py); this module imports nothing heavy (no torch,
no numpy: `radfield info` and the CLI's argument checks use it).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from radfield.errors import RadfieldError

RUN_MARKER = "radfield-run.json"
CONFIG_FILE = "config.yaml"
HASH_CACHE = "hashes.json"
LOCK = ".lock"
MANIFEST = "manifest.json"
_SCRATCH = re.compile(r"(.+\.(tmp|old)-.+)|(\..+\.tmp)")  # leftovers of a killed invocation

# the products commands read: (stage, file name inside its folder); the writers import these names
SFM_STAGE, SFM_DATASET = "sfm", "colmap"                  # stages/sfm.py
NORMALIZATION_FILE = "normalization.json"                 # datasets/sfm.py, inside SFM_DATASET
DATA_STAGE, SCENE_FILE = "data", "scene.json"             # datasets/scene.py (SCENE)
ENVELOPE_STAGE, ENVELOPE_FILE = "envelope", "envelope.ply"  # stages/envelope.py
CAGE_STAGE, CAGE_FILE = "tetra", "cage.npz"               # core/geometry/cage.py (CAGE_NPZ)
MODEL_STAGE, MODEL_FILE = "train", "model.safetensors"    # stages/train.py; edit/field.py (EDIT_MODEL)
LOG_FILE, CURVES_FILE = "log.jsonl", "curves.png"         # stages/train.py: the training log and its plot
CHECKPOINT_FILE = "checkpoint.safetensors"                # stages/train.py, inside train.work/
BIND_STAGE, BINDING_FILE = "bind", "model_binding.npz"    # stages/bind.py; edit/field.py (EDIT_BINDING)
EVAL_STAGE, METRICS_FILE = "eval", "metrics.json"         # evaluation/evaluate.py
EDIT_STAGE = "edit"                                       # `radfield edit` writes an edited run's field here
IMPORT_DIR, IMPORT_RECORD = "import", "import.json"       # stages/imported.py: an imported run's input
EDIT_SPEC = "spec.yaml"                                   # the spec an edited run was made with, in edit/


def is_run_dir(path: str | Path) -> bool:
    """Whether `path` is a radfield run directory (holds the run marker)."""
    return (Path(path) / RUN_MARKER).is_file()


def read_manifest(stage_dir: str | Path) -> dict[str, Any] | None:
    """The manifest of a finished stage (or of an edited run's edit/), or None: never run, or
    unreadable (then the stage re-runs)."""
    try:
        manifest = json.loads((Path(stage_dir) / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return manifest if isinstance(manifest, dict) and manifest.get("done") is True else None


def model_file(path: str | Path) -> Path:
    """A model file, or the final model of a run directory (which must exist)."""
    path = Path(path)
    if path.is_dir():
        model = Run(path).model
        if not model.is_file():
            raise RadfieldError(f"{path}: run directory has no trained model yet ({model} is missing)")
        return model
    if not path.exists():
        raise RadfieldError(f"{path}: no such model file or run directory")
    return path


def is_scratch(name: str) -> bool:
    """Whether an entry of a run directory is what a killed invocation left half-written."""
    return _SCRATCH.fullmatch(name) is not None


class Run:
    """A run directory, made or to be made: `Run(path)` checks nothing (the pipeline creates runs
    through it), `Run.open(path)` insists that `path` is one. Paths are returned whether or not the
    file exists, except where a property says it returns None for a missing one."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    @classmethod
    def open(cls, path: str | Path) -> "Run":
        """The run at `path`; a RadfieldError when `path` is not a radfield run directory."""
        if not is_run_dir(path):
            raise RadfieldError(f"{path} is not a radfield run directory")
        return cls(path)

    def __repr__(self) -> str:
        return f"Run({str(self.path)!r})"

    @property
    def exists(self) -> bool:
        return is_run_dir(self.path)

    # --- the run's own files ------------------------------------------------------------------

    @property
    def marker_file(self) -> Path:
        return self.path / RUN_MARKER

    @property
    def config_file(self) -> Path:
        return self.path / CONFIG_FILE

    @property
    def hash_file(self) -> Path:
        return self.path / HASH_CACHE

    @property
    def lock_file(self) -> Path:
        return self.path / LOCK

    def marker(self) -> dict[str, Any]:
        """The run marker's content ({"input": path or None, "created": ISO time, ...})."""
        try:
            marker = json.loads(self.marker_file.read_text(encoding="utf-8"))
        except (OSError, ValueError) as error:
            raise RadfieldError(f"{self.path}: damaged {RUN_MARKER} ({error})") from error
        if not isinstance(marker, dict):
            raise RadfieldError(f"{self.path}: damaged {RUN_MARKER}")
        return marker

    @property
    def input(self) -> Path | None:
        """The INPUT the run was made from, as recorded (None: not recorded)."""
        source = self.marker().get("input")
        return None if source is None else Path(source)

    def stage_names(self) -> list[str]:
        """Stages in the order of the run's config, then any other folder with a manifest (edit/).
        An edited run has no stages of its own (its config is the source's, whose stages were run
        there, not here): only its folders with a manifest, i.e. edit/."""
        import yaml

        from radfield.util.yamlfile import parse_yaml

        names: list[str] = []
        if not self.is_edited:
            try:
                config = parse_yaml(self.config_file.read_text(encoding="utf-8"))
                names = [str(name) for name in config.get("stages", [])]
            except (OSError, yaml.YAMLError, AttributeError):
                pass  # no readable config: fall back to what is on disk
        extra = sorted(p.parent.name for p in self.path.glob(f"*/{MANIFEST}") if p.parent.name not in names)
        return names + extra

    # --- stages -------------------------------------------------------------------------------

    def stage_dir(self, stage: str) -> Path:
        """Where a stage's outputs live once it has succeeded."""
        return self.path / stage

    def artifact(self, stage: str, name: str) -> Path:
        """One output of a stage (`name` as the stage module declares it)."""
        return self.stage_dir(stage) / name

    def manifest_file(self, stage: str) -> Path:
        return self.stage_dir(stage) / MANIFEST

    def manifest(self, stage: str) -> dict[str, Any] | None:
        """The stage's manifest when it has finished, else None."""
        return read_manifest(self.stage_dir(stage))

    def work_dir(self, stage: str) -> Path:
        """A stage's scratch that survives a failed attempt (checkpoints)."""
        return self.path / f"{stage}.work"

    def tmp_dir(self, stage: str, token: str) -> Path:
        """Where an attempt of a stage writes its outputs before they are swapped in."""
        return self.path / f"{stage}.tmp-{token}"

    @staticmethod
    def old_dir(tmp_dir: Path) -> Path:
        """Where a stage's previous outputs wait while `tmp_dir` (a tmp_dir) replaces them."""
        return tmp_dir.with_name(tmp_dir.name.replace(".tmp-", ".old-", 1))

    def scratch(self) -> list[Path]:
        """What killed invocations left half-written in the run (never read, so never trusted)."""
        return [path for path in self.path.iterdir() if is_scratch(path.name)]

    # --- products -----------------------------------------------------------------------------

    @property
    def edit_dir(self) -> Path:
        """An edited run's field (model, cage, binding, spec, manifest)."""
        return self.path / EDIT_STAGE

    @property
    def import_dir(self) -> Path:
        """An imported run's input: the model's renders, the model converted, import.json."""
        return self.path / IMPORT_DIR

    def imported_from(self) -> dict[str, Any] | None:
        """An imported run's import.json ({"source", "format", "kind", "primitives", ...}), or None:
        not an imported run (an edited run answers for the run it descends from)."""
        run = self.source_run() if self.is_edited else self
        try:
            record = json.loads((run.import_dir / IMPORT_RECORD).read_text(encoding="utf-8")) if run else None
        except (OSError, ValueError):
            return None
        return record if isinstance(record, dict) else None

    @property
    def edit_spec(self) -> Path:
        """The spec an edited run was made with."""
        return self.edit_dir / EDIT_SPEC

    @property
    def trained_model(self) -> Path:
        return self.artifact(MODEL_STAGE, MODEL_FILE)

    @property
    def is_edited(self) -> bool:
        """Whether this is a run `radfield edit` wrote (its final model is edit/'s)."""
        return (self.edit_dir / MODEL_FILE).is_file()

    @property
    def model(self) -> Path:
        """The final model: an edited run's edit/model.safetensors, else the train stage's."""
        return self.edit_dir / MODEL_FILE if self.is_edited else self.trained_model

    @property
    def reconstructed_cage(self) -> Path:
        """The tetra stage's cage."""
        return self.artifact(CAGE_STAGE, CAGE_FILE)

    @property
    def cage(self) -> Path | None:
        """The cage the final model is bound to (an edited run's, in its edited pose), or None."""
        cage = self.edit_dir / CAGE_FILE if self.is_edited else self.reconstructed_cage
        return cage if cage.is_file() else None

    @property
    def binding(self) -> Path | None:
        """The final model's binding to its cage, or None: an edited run's, else the bind stage's
        (runs made before the bind stage existed have it in train/)."""
        if self.is_edited:
            candidates = [self.edit_dir / BINDING_FILE]
        else:
            candidates = [self.artifact(BIND_STAGE, BINDING_FILE), self.artifact(MODEL_STAGE, BINDING_FILE)]
        return next((path for path in candidates if path.is_file()), None)

    @property
    def scene(self) -> Path:
        return self.artifact(DATA_STAGE, SCENE_FILE)

    @property
    def envelope(self) -> Path:
        return self.artifact(ENVELOPE_STAGE, ENVELOPE_FILE)

    @property
    def sfm_dataset(self) -> Path:
        """The posed COLMAP dataset the sfm stage makes of a folder of photos."""
        return self.artifact(SFM_STAGE, SFM_DATASET)

    @property
    def normalization(self) -> Path:
        """The SfM normalisation of a run made from photos (x = scale · (x_sfm − center))."""
        return self.sfm_dataset / NORMALIZATION_FILE

    @property
    def metrics(self) -> Path:
        """The eval stage's metrics.json."""
        return self.artifact(EVAL_STAGE, METRICS_FILE)

    @property
    def checkpoint(self) -> Path:
        """The checkpoint an interrupted training leaves in train.work/."""
        return self.work_dir(MODEL_STAGE) / CHECKPOINT_FILE

    @property
    def edited_from(self) -> Path | None:
        """The run directory or model file an edited run was made from, as recorded (None: not an
        edited run)."""
        source = self.marker().get("edited_from") if self.is_edited else None
        return None if source is None else Path(source)

    def source_run(self) -> "Run | None":
        """The reconstructed run an edited run descends from (through edits of edits), or None: a
        reconstructed run, or one edited from a model file or from a run that no longer exists."""
        run, seen = self, set()
        while run.is_edited:
            source = run.edited_from
            if source is None or not is_run_dir(source) or source.resolve() in seen:
                return None
            seen.add(source.resolve())
            run = Run(source)
        return None if run is self else run

    def dataset_scene(self) -> Path | None:
        """The data stage's scene.json that describes the run's cameras: its own, or for an edited
        run its source run's (an edit keeps the world frame, so the source's cameras still view
        it); None when there is none."""
        run = self.source_run() if self.is_edited else self
        return run.scene if run is not None and run.scene.is_file() else None

    def dataset(self) -> Path | None:
        """The posed dataset the run trained on: the SfM output for photos, else the run's input
        (None: an edited run made from a model file records none)."""
        return self.sfm_dataset if self.sfm_dataset.is_dir() else self.input
