"""Cached, atomic execution of pipeline stages in a run directory (its layout: radfield/run.py).

A stage writes into RUN/<stage>.tmp-XXXX/, which replaces RUN/<stage>/ only when the stage has
succeeded; RUN/<stage>.work/ keeps what must survive a failed attempt (checkpoints).

Cache rule: a stage is skipped when its manifest records the same format version, the same hash of
its config sections and the same content hashes of its input artifacts, and its outputs on disk
still match the hashes recorded. Hashes are of content, so an upstream stage that re-runs and
writes byte-identical outputs leaves downstream stages cached; any change propagates naturally.
The `device` key is deliberately not part of any cache key: moving a run to another device
resumes it rather than recomputing it.
"""

from __future__ import annotations

import contextlib
import copy
import datetime
import difflib
import fcntl
import hashlib
import json
import numbers
import os
import secrets
import shutil
import sys
import time
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from radfield.util.atomic import atomic_write_text
from radfield.errors import RadfieldError
from radfield.pipeline.config import save_resolved, section
from radfield.pipeline.schema import Config, plain
from radfield.run import MANIFEST, Run, read_manifest

INPUT = "input"  # artifact name of the user's input (the dataset path); no stage produces it
RESERVED_FIGURES = frozenset({"done", "seconds", "applicable", "reason"})  # info keys figures cannot take

Figures = Mapping[str, int | float | str | bool | None]


class NotApplicable(Exception):
    """Raised by a stage function when the stage has nothing to do for this run (SfM on a posed
    dataset, say); the message says why. The stage is recorded as done without outputs, and the
    stages that consume its artifacts receive None for them."""


@dataclass(frozen=True)
class Context:
    """What a stage function gets.

    Write outputs into `tmp` (`outputs[name]` are the declared paths there); they replace
    `stage_dir` only when the function returns. `work` persists across failed attempts (for
    checkpoints) and is wiped when the stage's inputs, config or version change, on `--force`,
    and after success.
    """

    name: str
    run_dir: Path
    stage_dir: Path  # where the outputs will live once the stage succeeds; do not write here
    tmp: Path
    work: Path
    config: dict[str, Any]  # section(config, stage.config_keys): nested as in the full config
    inputs: dict[str, Path | None]  # None when the producing stage was not applicable
    outputs: dict[str, Path]
    log: Callable[[str], None]  # a line for the user (silent under --quiet)
    quiet: bool  # no progress bars either
    device: str

    @property
    def seed(self) -> int:
        """The run's seed; the stage must list "seed" in its config_keys so that it is hashed."""
        if "seed" not in self.config:
            raise RuntimeError(f"stage {self.name} uses the seed without declaring 'seed' in config_keys")
        return int(self.config["seed"])


@dataclass(frozen=True)
class Stage:
    """A stage declaration. `run(ctx)` returns figures for the manifest (counts, metrics) or None.

    `config_keys` are the dotted config keys the stage depends on (e.g. "train", "render",
    "seed"); `inputs` are artifact names produced by earlier stages (or INPUT); `outputs` are the
    file or directory names it writes into its stage directory, unique across the pipeline.
    Bump `version` when the format of the outputs or the meaning of the stage changes.
    `resolve(config, input_path)`, when given, fills in (in place, on the plain config) the values
    that an automatic setting takes from the input, before anything is hashed or saved: the cache
    keys and RUN/config.yaml then hold the number the stage uses, and so does every later command
    (the data stage: data.downscale null).
    """

    name: str
    run: Callable[[Context], Figures | None]
    config_keys: tuple[str, ...] = ()
    inputs: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()
    version: int = 1
    resolve: Callable[[dict[str, Any], Path | None], None] | None = None


def run_pipeline(
    stages: Sequence[Stage],
    run_dir: Path,
    config: Config | Mapping[str, Any],
    *,
    input_path: Path | None = None,
    force: Collection[str] = frozenset(),
    from_stage: str | None = None,
    until_stage: str | None = None,
    quiet: bool = False,
    log: Callable[[str], None] | None = None,
) -> dict[str, str]:
    """Bring the run directory up to date: run the stages named by `config.stages`, in that
    order, skipping those whose manifest matches.

    `config` is the resolved config, typed (pipeline/schema.py's `Config`) or a nested mapping
    (load_config's result, or a toy pipeline's); once the planned stages' `resolve` have filled in
    its automatic values, each stage's cache key hashes the part of it that its `config_keys` name,
    `section(config, stage.config_keys)`, and RUN/config.yaml records it all.
    `stages` declares every stage that may run. `force` names stages to re-run regardless;
    `from_stage` forces it and every later stage; `until_stage` stops after it. `input_path` is
    the INPUT artifact. Everything a user can get wrong (stage names, a run directory that is not
    a radfield run or was made from another input) is checked before the run directory is
    touched. Returns {stage: "ran" | "cached" | "not applicable"} for the stages visited.
    """
    say = (lambda _line: None) if quiet else (log or _print_stderr)
    layout = Run(run_dir)
    input_path = Path(input_path).resolve() if input_path is not None else None
    resolved = plain(config)   # RUN/config.yaml
    plan, forced = _plan(stages, resolved["stages"], set(force), from_stage, until_stage)
    _check_input(plan, input_path)
    _check_run_dir(layout, plan, input_path, forced)
    for stage in plan:
        if stage.resolve is not None:
            stage.resolve(resolved, input_path)
    sections = {stage.name: section(resolved, stage.config_keys) for stage in plan}

    layout.path.mkdir(parents=True, exist_ok=True)
    with _locked(layout):
        _write_marker(layout, input_path)
        save_resolved(resolved, layout.config_file)
        _remove_scratch(layout)
        run = _Invocation(layout, HashCache(layout.hash_file), str(resolved.get("device", "cpu")), quiet, say)
        run.available[INPUT] = input_path
        try:
            return {stage.name: _bring_up_to_date(run, stage, sections[stage.name], stage.name in forced)
                    for stage in plan}
        finally:
            run.hashes.save()


# --- planning and checks (no writes) ----------------------------------------------------------


def _plan(
    stages: Sequence[Stage], order: Sequence[str], force: set[str], from_stage: str | None, until_stage: str | None
) -> tuple[list[Stage], set[str]]:
    """The stages to visit, in order, and the set of those to re-run unconditionally."""
    declared = {stage.name: stage for stage in stages}
    for name in order:
        if name not in declared:
            raise RadfieldError(f"config key stages names {name}, which is not a stage ({', '.join(declared)})")
    plan = [declared[name] for name in order]
    names = [stage.name for stage in plan]
    asked = [("--from", from_stage), ("--until", until_stage)] + [("--force", n) for n in sorted(force)]
    for flag, asked_name in asked:
        if asked_name is not None and asked_name not in names:
            close = difflib.get_close_matches(asked_name, names, n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise RadfieldError(f"{flag} {asked_name}: no such stage{hint}; stages are {', '.join(names)}")
    if from_stage is not None and until_stage is not None and names.index(from_stage) > names.index(until_stage):
        raise RadfieldError(f"--from {from_stage} comes after --until {until_stage}")
    if until_stage is not None:
        plan = plan[: names.index(until_stage) + 1]
    if from_stage is not None:
        force |= set(names[names.index(from_stage) :])
    _check_artifacts(stages, plan)
    return plan, {stage.name for stage in plan} & force


def _check_artifacts(stages: Sequence[Stage], plan: Sequence[Stage]) -> None:
    """Every input is INPUT or produced by an earlier stage of the plan; output names are unique."""
    producer: dict[str, str] = {}
    for stage in stages:
        for name in stage.outputs:
            if name in producer or name in (INPUT, MANIFEST) or Path(name).is_absolute() or ".." in Path(name).parts:
                raise ValueError(f"stage {stage.name}: bad or duplicate output name {name!r}")
            producer[name] = stage.name
    made = {INPUT}
    for stage in plan:
        for name in stage.inputs:
            if name not in made:
                source = producer.get(name)
                if source is None:
                    raise ValueError(f"stage {stage.name}: no stage produces its input {name!r}")
                raise RadfieldError(f"stage {stage.name} needs {name} from stage {source}, "
                                    f"which does not run before it (config key stages)")
        made.update(stage.outputs)


def _check_input(plan: Sequence[Stage], input_path: Path | None) -> None:
    if not any(INPUT in stage.inputs for stage in plan):
        return
    if input_path is None:
        raise ValueError("the plan reads INPUT but run_pipeline got no input_path")
    if not input_path.exists():
        raise RadfieldError(f"input {input_path} does not exist")


def _check_run_dir(layout: Run, plan: Sequence[Stage], input_path: Path | None, forced: set[str]) -> None:
    """Refuse to write into a folder that is not ours, or a run made from another input. A folder
    that holds nothing but the run's own INPUT (an imported run's RUN/import/) is a new run."""
    run_dir = layout.path
    if run_dir.exists() and not run_dir.is_dir():
        raise RadfieldError(f"run directory {run_dir} exists and is not a directory")
    if not run_dir.exists() or not [p for p in run_dir.iterdir() if p != layout.lock_file and p.resolve() != input_path]:
        return
    if not layout.exists:
        raise RadfieldError(f"{run_dir} exists and is not a radfield run directory; choose another output "
                            f"or remove it")
    previous = layout.marker().get("input")
    if input_path is None or previous is None or Path(previous) == input_path:
        return
    readers = [stage.name for stage in plan if INPUT in stage.inputs]
    if not set(readers) & forced:
        hint = f", or add --force {readers[0]} to rebuild it from the new input" if readers else ""
        raise RadfieldError(f"run directory {run_dir} was made from {previous}, not {input_path}; "
                            f"choose another output{hint}")


# --- one stage --------------------------------------------------------------------------------


@dataclass
class _Invocation:
    """What every stage of one `run_pipeline` call shares."""

    layout: Run
    hashes: HashCache
    device: str
    quiet: bool
    say: Callable[[str], None]
    available: dict[str, Path | None] = field(default_factory=dict)  # artifact -> path, as stages finish


def _bring_up_to_date(run: _Invocation, stage: Stage, config: dict[str, Any], forced: bool) -> str:
    """Skip or run one stage, then publish its artifacts to the later stages."""
    stage_dir = run.layout.stage_dir(stage.name)
    inputs = {name: run.available[name] for name in stage.inputs}
    key = {
        "format_version": stage.version,
        "config_hash": _digest(config),
        "inputs": {name: _input_hash(run, name, path) for name, path in inputs.items()},
    }
    previous = read_manifest(stage_dir)
    reason = "forced" if forced else _stale_reason(stage, previous, key, config, stage_dir, run.hashes)
    if previous is not None and reason is None:
        run.say(f"{stage.name}: up to date")
        # checkpoints of an interrupted --force attempt are of no use once the result is valid
        shutil.rmtree(run.layout.work_dir(stage.name), ignore_errors=True)
        manifest, outcome = previous, "cached"
    else:
        run.say(f"{stage.name}: running ({reason})")
        manifest = _execute(run, stage, config, inputs, key, forced)
        outcome = "ran" if manifest["applicable"] else "not applicable"
    for name in stage.outputs:
        run.available[name] = stage_dir / name if manifest["applicable"] else None
    return outcome


def _stale_reason(
    stage: Stage,
    previous: dict[str, Any] | None,
    key: dict[str, Any],
    config: dict[str, Any],
    stage_dir: Path,
    hashes: HashCache,
) -> str | None:
    """Why the stage must run again, or None when its previous result is still valid."""
    if previous is None:
        return "no previous result"
    if previous.get("format_version") != key["format_version"]:
        return f"format version {previous.get('format_version')} -> {key['format_version']}"
    if previous.get("config_hash") != key["config_hash"]:
        changed = _changed_keys(previous.get("config", {}), config)
        return f"config changed: {', '.join(changed) or 'its sections'}"
    if previous.get("inputs") != key["inputs"]:
        old = previous.get("inputs") or {}
        changed = [name for name in key["inputs"] if old.get(name) != key["inputs"][name]]
        return f"input changed: {', '.join(changed) or 'inputs declared differently'}"
    recorded = previous.get("outputs") or {}
    if previous.get("applicable") and set(recorded) != set(stage.outputs):
        return "outputs declared differently"
    for name, digest in recorded.items():
        path = stage_dir / name
        if not path.exists() or hashes.artifact(path) != digest:
            return f"output {name} changed on disk"
    return None


def _execute(
    run: _Invocation,
    stage: Stage,
    config: dict[str, Any],
    inputs: dict[str, Path | None],
    key: dict[str, Any],
    forced: bool,
) -> dict[str, Any]:
    """Run the stage function into a temporary directory and swap it into place on success."""
    stage_dir = run.layout.stage_dir(stage.name)
    work = run.layout.work_dir(stage.name)
    _prepare_work(work, key, wipe=forced)
    tmp = run.layout.tmp_dir(stage.name, secrets.token_hex(4))
    tmp.mkdir()  # not mkdtemp: outputs get the umask's mode, not 0700
    try:
        ctx = Context(
            name=stage.name,
            run_dir=run.layout.path,
            stage_dir=stage_dir,
            tmp=tmp,
            work=work,
            config=copy.deepcopy(config),  # the stage may not alter what the manifest records
            inputs=dict(inputs),
            outputs={name: tmp / name for name in stage.outputs},
            log=lambda line: run.say(f"{stage.name}: {line}"),
            quiet=run.quiet,
            device=run.device,
        )
        started = _now()
        clock = time.perf_counter()
        applicable, why = True, None
        try:
            figures = _checked_figures(stage, stage.run(ctx) or {})
        except NotApplicable as error:
            applicable, why, figures = False, str(error) or "not applicable", {}
            shutil.rmtree(tmp)
            tmp.mkdir()
        except RadfieldError as error:
            raise RadfieldError(f"{stage.name}: {error}") from error
        seconds = time.perf_counter() - clock
        outputs: dict[str, str] = {}
        if applicable:
            missing = [name for name in stage.outputs if not (tmp / name).exists()]
            if missing:
                raise RuntimeError(f"stage {stage.name} did not write its outputs {', '.join(missing)}")
            outputs = {name: run.hashes.artifact(tmp / name, cache_as=stage_dir / name) for name in stage.outputs}
        manifest = {
            "stage": stage.name,
            "done": True,
            "applicable": applicable,
            "reason": why,
            **key,
            "config": config,
            "outputs": outputs,
            "seconds": round(seconds, 3),
            "figures": figures,
            "started": started,
            "finished": _now(),
        }
        atomic_write_text(tmp / MANIFEST, json.dumps(manifest, indent=2) + "\n")
        _swap_in(tmp, stage_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    shutil.rmtree(work, ignore_errors=True)
    summary = "not applicable: " + str(why) if not applicable else format_figures(figures)
    run.say(f"{stage.name}: done in {seconds:.1f} s" + (f" ({summary})" if summary else ""))
    return manifest


def _prepare_work(work: Path, key: dict[str, Any], wipe: bool) -> None:
    """Keep the scratch of an interrupted attempt only if it was made for the same inputs,
    config and version (a checkpoint of another config must not be resumed)."""
    stamp = work / ".key.json"
    stored = None
    if stamp.is_file():
        with contextlib.suppress(OSError, ValueError):
            stored = json.loads(stamp.read_text(encoding="utf-8"))
    if work.exists() and (wipe or stored != key):
        shutil.rmtree(work)
    work.mkdir(exist_ok=True)
    atomic_write_text(stamp, json.dumps(key))


def _swap_in(tmp: Path, stage_dir: Path) -> None:
    """Replace `stage_dir` by `tmp`. Killed in between, neither is trusted: the stage re-runs."""
    if stage_dir.exists():
        old = Run.old_dir(tmp)
        os.rename(stage_dir, old)
        os.rename(tmp, stage_dir)
        shutil.rmtree(old)
    else:
        os.rename(tmp, stage_dir)


def _checked_figures(stage: Stage, figures: Figures) -> dict[str, Any]:
    """Figures as JSON scalars (numpy scalars become int/float); anything else is a bug."""
    out: dict[str, Any] = {}
    for name, value in figures.items():
        if not isinstance(name, str) or name in RESERVED_FIGURES:
            raise TypeError(f"stage {stage.name}: figure name {name!r} is reserved or not a string")
        if value is None or isinstance(value, (bool, str)):
            out[name] = value
        elif isinstance(value, numbers.Integral):
            out[name] = int(value)
        elif isinstance(value, numbers.Real):
            out[name] = float(value)
        else:
            raise TypeError(f"stage {stage.name}: figure {name} = {value!r} is not a JSON scalar")
    return out


def format_figures(figures: Mapping[str, Any]) -> str:
    """Figures on one line: `images=100 train_psnr=31.2`."""
    return " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in figures.items())


# --- run directory housekeeping ---------------------------------------------------------------


@contextlib.contextmanager
def _locked(layout: Run) -> Iterator[None]:
    """One invocation at a time per run directory (the lock dies with the process)."""
    with open(layout.lock_file, "a+") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RadfieldError(f"run directory {layout.path} is in use by another radfield process") from None
        yield


def _write_marker(layout: Run, input_path: Path | None) -> None:
    marker: dict[str, Any] = {"kind": "radfield-run", "created": _now(), "input": None}
    if layout.exists:
        marker.update(layout.marker())
    if input_path is not None:
        marker["input"] = str(input_path)
    atomic_write_text(layout.marker_file, json.dumps(marker, indent=2) + "\n")


def _remove_scratch(layout: Run) -> None:
    """Delete what a killed invocation left half-written (never read, so never trusted)."""
    for path in layout.scratch():
        shutil.rmtree(path) if path.is_dir() else path.unlink()


# --- hashing ----------------------------------------------------------------------------------


class HashCache:
    """sha256 of files and directories, cached by (size, mtime_ns) in a JSON file.

    A directory's hash covers its files' sorted relative paths and contents. Only entries used
    in this invocation are written back, so the cache does not grow with stale paths.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.old: dict[str, list[Any]] = {}
        self.used: dict[str, list[Any]] = {}
        with contextlib.suppress(OSError, ValueError):
            loaded = json.loads(path.read_text(encoding="utf-8"))
            if isinstance(loaded, dict):
                self.old = loaded

    def artifact(self, path: Path, cache_as: Path | None = None, exclude: Path | None = None) -> str:
        """Hash of a file or directory. `cache_as` records the entries under the path the
        artifact will be moved to; `exclude` is a subtree left out (a run dir inside INPUT)."""
        if path.is_file():
            return self._file(path, cache_as or path)
        digest = hashlib.sha256()
        for file in _files_under(path, exclude):
            relative = file.relative_to(path).as_posix()
            file_hash = self._file(file, (cache_as or path) / relative)
            digest.update(f"{relative}\0{file_hash}\n".encode())
        return digest.hexdigest()

    def save(self) -> None:
        atomic_write_text(self.path, json.dumps(self.used))

    def _file(self, path: Path, key_path: Path) -> str:
        stat = path.stat()
        key = str(key_path.resolve())
        entry = self.used.get(key) or self.old.get(key)
        if not (isinstance(entry, list) and len(entry) == 3 and entry[:2] == [stat.st_size, stat.st_mtime_ns]):
            digest = hashlib.sha256()
            with open(path, "rb") as handle:
                for chunk in iter(lambda: handle.read(1 << 20), b""):
                    digest.update(chunk)
            entry = [stat.st_size, stat.st_mtime_ns, digest.hexdigest()]
        self.used[key] = entry
        return str(entry[2])


def _files_under(root: Path, exclude: Path | None) -> list[Path]:
    skip = exclude.resolve() if exclude is not None else None
    files: list[Path] = []
    for directory, subdirs, names in os.walk(root):
        if skip is not None:
            subdirs[:] = [d for d in subdirs if (Path(directory) / d).resolve() != skip]
        files.extend(Path(directory) / name for name in names)
    return sorted(files, key=lambda file: file.relative_to(root).as_posix())


def _input_hash(run: _Invocation, name: str, path: Path | None) -> str | None:
    if path is None:
        return None
    # a run directory inside the dataset folder must not make the dataset look changed
    return run.hashes.artifact(path, exclude=run.layout.path if name == INPUT else None)


# --- small helpers ----------------------------------------------------------------------------


def _digest(value: Any) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()


def _changed_keys(old: Any, new: Any, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two nested config sections."""
    if isinstance(old, dict) and isinstance(new, dict):
        changed: list[str] = []
        for name in sorted(set(old) | set(new)):
            changed += _changed_keys(old.get(name), new.get(name), f"{prefix}{name}.")
        return changed
    return [] if old == new else [prefix.rstrip(".")]


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _print_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)
