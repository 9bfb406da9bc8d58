"""The pipeline configuration: defaults from `pipeline.yaml`, user overrides, validation.

The schema is not written down twice: every key, its type and (for lists) its length are read
off the defaults in `pipeline.yaml` itself. The few facts a default value cannot express live in
the small tables below (keys whose default is `null`, the stage list, closed sets of values).

A resolved config is a plain nested dict of YAML scalars and lists. Precedence, lowest first:
`pipeline.yaml` < `--config FILE` < `options` (the CLI's dedicated flags) < `--set key=value`.
"""

from __future__ import annotations

import copy
import difflib
import functools
import importlib.resources
import json
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from radfield.util.atomic import atomic_write_text
from radfield.util.yamlfile import parse_yaml, yaml_problem
from radfield.util.ranges import AT_LEAST_0, AT_LEAST_1, FRACTION, POSITIVE, Range
from radfield.errors import RadfieldError

DEFAULTS_NAME = "pipeline.yaml"

# Keys whose default is null, with the type a non-null value must have.
NULLABLE: dict[str, type] = {"train.max_primitives": int, "train.log_every": int}
# List keys whose value is any selection of the default's items, in any order (the stage list);
# other lists keep the length of their default.
SELECTIONS: frozenset[str] = frozenset({"stages"})


def _primitive_kinds() -> tuple[str, ...]:
    """The registered primitive kinds (radfield.core.kinds, imported when a config is checked: it needs torch)."""
    from radfield.core import kinds

    return kinds.names()


# Keys that only take one of a few values (a callable: values known only once their registry is
# imported, which this light module does not do at import time).
CHOICES: dict[str, tuple[str, ...] | Callable[[], tuple[str, ...]]] = {
    # COLMAP's models that undistort to a pinhole camera
    "sfm.camera_model": ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV",
                         "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE"),
    "envelope.source": ("auto", "points", "mesh", "hull", "triangulate", "none"),
    "envelope.method": ("auto", "poisson", "ball_pivoting", "alpha", "convex"),
    "train.primitive": _primitive_kinds,
    "init.source": ("auto", "mesh", "points", "random"),
    "eval.split": ("train", "val", "test"),
    "data.time": ("auto", "ignore"),
    "data.light": ("auto", "ignore"),
}

_TYPE_NAMES = {bool: "a boolean", int: "an integer", float: "a number", str: "a string"}

COMMAND_LINE = "command line"   # the source of `options`: the CLI's own flags
# The flag that sets a key directly, the same on every command: its error lines name the flag the
# user typed, not the key (`--downscale must be at least 1, got 0`).
OPTION_FLAGS = {"seed": "--seed", "device": "--device", "data.downscale": "--downscale",
                "data.background": "--background", "train.primitive": "--primitive",
                "train.iterations": "--iterations", "train.max_primitives": "--max-primitives",
                "render.near": "--near", "bake.min_weight": "--min-weight"}


# The range of every numeric key of pipeline.yaml (tests/test_pipeline.py: every one is listed, every
# default inside): an out-of-range value is refused when it is set (one line naming where it came
# from), before the run directory is touched, so a mistake never replaces a trained model by a
# broken one.
RANGES: dict[str, Range] = {
    "seed": AT_LEAST_0,
    "data.downscale": AT_LEAST_1,
    "data.background": FRACTION,
    "data.test_every": Range(2),
    "data.val_every": Range(0, note="0 = no val split"),
    "sfm.num_threads": Range(1, also=-1, note="-1 = all cores"),
    "sfm.max_image_size": AT_LEAST_1,
    "sfm.max_num_features": AT_LEAST_1,
    "sfm.exhaustive_max_images": AT_LEAST_1,
    "sfm.sequential_overlap": AT_LEAST_1,
    "sfm.min_registered_fraction": Range(0, 1, open_low=True),
    "sfm.target_radius": POSITIVE,
    "envelope.outlier_std": POSITIVE,
    "envelope.poisson_depth": Range(1, 16),
    "envelope.wrap_alpha": POSITIVE,
    "envelope.offset": POSITIVE,
    "envelope.target_faces": Range(20),
    "envelope.hull_resolution": Range(8),
    "envelope.num_threads": AT_LEAST_1,
    "tetra.edge_length_fac": Range(0, 1, open_low=True, open_high=True),
    "tetra.epsilon": Range(0, 1, open_low=True, open_high=True),
    "tetra.num_threads": AT_LEAST_1,
    "init.num_points": AT_LEAST_1,
    "init.w1_scale": Range(0, 10),
    "init.neural_radius": Range(0, 10, note="0 = automatic"),
    "init.cage_fraction": FRACTION,
    "train.iterations": AT_LEAST_1,
    "train.max_primitives": AT_LEAST_1,
    "train.sh_degree": Range(0, 3),
    "train.sh_increase_every": AT_LEAST_1,
    "train.lambda_dssim": FRACTION,
    "train.lambda_aniso": AT_LEAST_0,
    "train.lambda_w1": Range(0, note="0 = off"),
    "train.lambda_density": Range(0, note="0 = off"),
    "train.frequency_cap": Range(0, note="0 = no cap"),
    "train.frequency_bound": Range(0, note="0 = no bound"),
    "train.nonnegative_density": Range(0, 180, note="degrees, 0 = off"),
    "train.ray_jitter": Range(0, 1, note="pixels, 0 = off"),
    "train.min_footprint": Range(0, 8, note="pixels, 0 = off"),
    **{f"train.lr.{group}": Range(0, note="0 freezes the group")
       for group in ("means", "log_scales", "quats", "sh_dc", "sh_rest", "mlp", "color", "opacities")},
    "train.means_lr_final_ratio": Range(0, 1, open_low=True),
    "train.densify.start": AT_LEAST_0,
    "train.densify.stop": AT_LEAST_0,
    "train.densify.every": AT_LEAST_1,
    "train.densify.grad_threshold": AT_LEAST_0,
    "train.densify.prune_threshold": AT_LEAST_0,
    "train.densify.grow_scale": POSITIVE,
    "train.densify.prune_scale": POSITIVE,
    "train.densify.gaussian.grad_threshold": AT_LEAST_0,
    "train.densify.gaussian.min_opacity": Range(0, 1, open_high=True),
    "train.densify.gaussian.prune_scale": POSITIVE,
    "train.densify.gaussian.opacity_reset_every": AT_LEAST_1,
    "train.checkpoint_every": AT_LEAST_1,
    "train.batch_views": AT_LEAST_1,
    "train.eval_every": Range(0, note="0 = never"),
    "train.log_every": Range(1, note="null: 1 on the CPU, 50 on a GPU"),
    "distributed.timeout": POSITIVE,
    "distributed.sync_check_every": Range(0, note="0 = only at the start"),
    "render.near": POSITIVE,
    "render.omega0": POSITIVE,
    "render.hidden": Range(1, 64),
    "render.supersample": Range(1, 4, note="1 = off"),
    "render.time_frequency": Range(0, 100, open_low=True, note="1: the paper's ω; 2π: one period"),
    "bake.min_weight": Range(0, 1, open_high=True),
}


def defaults_path() -> Path:
    """Where `pipeline.yaml` is: inside the `radfield` package (pyproject's package-data ships it)."""
    installed = Path(str(importlib.resources.files("radfield").joinpath(DEFAULTS_NAME)))
    if installed.is_file():
        return installed
    raise RadfieldError(f"{DEFAULTS_NAME} not found (looked at {installed})")


def load_defaults() -> dict[str, Any]:
    """The defaults as a fresh nested dict."""
    return copy.deepcopy(_schema())


def load_config(
    config_file: Path | None = None,
    sets: Sequence[str] = (),
    options: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Resolve the config: defaults, then `config_file` (partial YAML), then `options`
    ({dotted key: value}, the CLI's own flags), then `sets` ("key=value" strings).

    Raises RadfieldError naming the key and where it came from on any unknown key or bad value.
    """
    config = load_defaults()
    if config_file is not None:
        _merge(config, _read_yaml_mapping(Path(config_file)), source=str(config_file))
    for key, value in (options or {}).items():
        set_key(config, key, value, source=COMMAND_LINE)
    for text in sets:
        key, value = parse_set(text)
        set_key(config, key, value, source=f"--set {text}")
    return config


def run_config(run, options: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """A run's resolved config (its RUN/config.yaml; the defaults for a run without one, such as a
    run edited from a model file), with `options` ({"data.downscale": 2, ...}) set over it."""
    return load_config(run.config_file if run.config_file.is_file() else None, options=options or {})


def parse_set(text: str) -> tuple[str, Any]:
    """Split one `--set key=value` into the dotted key and its value parsed as a YAML scalar or
    list (`500`, `1e-4`, `[1, 1, 1]`, `null`, `neural`)."""
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*", key):
        raise RadfieldError(f"--set expects key=value with a dotted key such as train.iterations=500, got {text!r}")
    try:
        value = parse_yaml(raw)
    except yaml.YAMLError as error:
        raise RadfieldError(f"--set {text}: cannot parse the value of {key} ({yaml_problem(error)})") from error
    if isinstance(value, dict):
        raise RadfieldError(f"--set {text}: {key} takes a single value; set the keys inside it one by one")
    return key, value


def set_key(config: dict[str, Any], key: str, value: Any, source: str) -> None:
    """Set one dotted key of a resolved config in place, validated against the defaults."""
    parts = key.split(".")
    node = config
    for depth, part in enumerate(parts[:-1]):
        if part not in node:
            _unknown(config, key, source)
        if not isinstance(node[part], dict):
            raise RadfieldError(f"{source}: config key {'.'.join(parts[: depth + 1])} is a value, not a section")
        node = node[part]
    leaf = parts[-1]
    if leaf not in node:
        _unknown(config, key, source)
    if isinstance(node[leaf], dict):
        example = next(iter(node[leaf]))
        raise RadfieldError(f"{source}: config key {key} is a section; set the keys inside it, e.g. {key}.{example}")
    node[leaf] = _checked(key, value, _default_of(key), source)


def section(config: Mapping[str, Any], keys: str | Iterable[str]) -> dict[str, Any]:
    """The part of `config` that a stage depends on: a deep copy holding only the given dotted
    keys, nested as in the full config.

    `section(cfg, "train")` is `{"train": {...}}`; `section(cfg, ["train", "render", "seed"])` is
    `{"train": {...}, "render": {...}, "seed": 0}`; `section(cfg, "train.lr")` is
    `{"train": {"lr": {...}}}`. A key missing from `config` is a bug in a stage declaration
    (KeyError).
    """
    out: dict[str, Any] = {}
    for key in [keys] if isinstance(keys, str) else keys:
        parts = key.split(".")
        node: Any = config
        target = out
        for part in parts[:-1]:
            node = node[part]
            target = target.setdefault(part, {})
        target[parts[-1]] = copy.deepcopy(node[parts[-1]])
    return out


def save_resolved(config: Mapping[str, Any], path: Path) -> None:
    """Write the resolved config as YAML, atomically (a reader never sees half a file)."""
    atomic_write_text(Path(path), yaml.safe_dump(dict(config), sort_keys=False, default_flow_style=None))


# --- validation -------------------------------------------------------------------------------

@functools.cache
def _schema() -> dict[str, Any]:
    """The defaults, read once per process: they are the schema (never mutate the result)."""
    defaults = _read_yaml_mapping(defaults_path())
    _check_schema(defaults)
    return defaults


def _default_of(key: str) -> Any:
    node: Any = _schema()
    for part in key.split("."):
        node = node[part]
    return node


def _merge(config: dict[str, Any], partial: Mapping[str, Any], source: str, prefix: str = "") -> None:
    """Apply a partial nested mapping (a `--config` file) onto `config`, key by key."""
    for name, value in partial.items():
        key = f"{prefix}{name}"
        try:
            target = _default_of(key)
        except (KeyError, TypeError):
            target = None  # unknown: set_key reports it with a suggestion
        if isinstance(target, dict) and value is None:
            continue  # `train:` with every key commented out overrides nothing
        if isinstance(target, dict) and isinstance(value, dict):
            _merge(config, value, source, prefix=f"{key}.")
        else:
            set_key(config, key, value, source)


def _checked(key: str, value: Any, default: Any, source: str) -> Any:
    """`value` if it fits the type of `default` (ints widened to float) and the key's range
    (RANGES; each item of a list), else RadfieldError."""
    if value is None:
        if key in NULLABLE:
            return None
        raise _bad(source, key, _describe(default, key), value)
    if isinstance(default, list):
        if not isinstance(value, list) or (key not in SELECTIONS and len(value) != len(default)):
            raise _bad(source, key, _describe(default, key), value)
        items = [_checked_scalar(key, item, type(default[0]), default, source, whole=value) for item in value]
        if key in SELECTIONS:
            _check_selection(key, items, default, source)
        return items
    expected = NULLABLE[key] if default is None else type(default)
    checked = _checked_scalar(key, value, expected, default, source, whole=value)
    choices = CHOICES[key]() if callable(CHOICES.get(key)) else CHOICES.get(key)   # callable: read when checked
    if choices is not None and checked not in choices:
        raise _bad(source, key, f"one of {', '.join(choices)}", value)
    return checked


def _checked_scalar(key: str, value: Any, expected: type, default: Any, source: str, whole: Any) -> Any:
    # bool is a subclass of int in Python; a config never means True when it says 1.
    if isinstance(value, bool) != (expected is bool):
        ok = False
    elif expected is float:
        ok = isinstance(value, (int, float))
    else:
        ok = isinstance(value, expected)
    if not ok:
        raise _bad(source, key, _describe(default, key), whole)
    allowed = RANGES.get(key)
    if allowed is not None and not allowed.holds(value):
        what = allowed.describe()
        raise _bad(source, key, f"{'numbers ' if isinstance(whole, list) else ''}{what}", whole)
    return float(value) if expected is float else value


def _bad(source: str, key: str, what: str, value: Any) -> RadfieldError:
    """The one error line of a value that does not fit: a flag's names the flag the user typed,
    any other's the source and the key."""
    if source == COMMAND_LINE and key in OPTION_FLAGS:
        return RadfieldError(f"{OPTION_FLAGS[key]} must be {what}, got {_show(value)}")
    return RadfieldError(f"{source}: config key {key} must be {what}, got {_show(value)}")


def _check_selection(key: str, items: list[Any], default: list[Any], source: str) -> None:
    for item in items:
        if item not in default:
            close = difflib.get_close_matches(item, default, n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise RadfieldError(f"{source}: config key {key}: unknown entry {_show(item)}{hint}; "
                                f"choose from {', '.join(default)}")
    if len(set(items)) != len(items):
        raise RadfieldError(f"{source}: config key {key} lists an entry twice: {_show(items)}")


def _show(value: Any) -> str:
    """A value as the user wrote it in YAML/JSON (true, not True)."""
    return json.dumps(value, default=str)


def _describe(default: Any, key: str) -> str:
    if isinstance(default, list):
        length = "" if key in SELECTIONS else f"{len(default)} "
        return f"a list of {length}{_TYPE_NAMES[type(default[0])].split(' ', 1)[1]}s"
    if default is None:
        return f"{_TYPE_NAMES[NULLABLE[key]]} or null"
    return _TYPE_NAMES[type(default)]


def _unknown(config: Mapping[str, Any], key: str, source: str) -> None:
    """Raise the unknown-key error, with the closest valid key as a suggestion."""
    valid = list(_all_keys(config))
    close = difflib.get_close_matches(key, valid, n=1, cutoff=0.6)
    hint = f" (did you mean {close[0]}?)" if close else ""
    raise RadfieldError(f"{source}: unknown config key {key}{hint}")


def _all_keys(config: Mapping[str, Any], prefix: str = "") -> Iterable[str]:
    for name, value in config.items():
        yield f"{prefix}{name}"
        if isinstance(value, dict):
            yield from _all_keys(value, prefix=f"{prefix}{name}.")


def _check_schema(defaults: Mapping[str, Any], prefix: str = "") -> None:
    """Catch a `pipeline.yaml` that cannot serve as a schema (a bug, not a user error)."""
    for name, value in defaults.items():
        key = f"{prefix}{name}"
        if isinstance(value, dict):
            _check_schema(value, prefix=f"{key}.")
        elif value is None and key not in NULLABLE:
            raise ValueError(f"{DEFAULTS_NAME}: {key} is null but not listed in NULLABLE")
        elif isinstance(value, list) and (not value or len({type(item) for item in value}) != 1):
            raise ValueError(f"{DEFAULTS_NAME}: {key} must be a non-empty list of one type")
        elif value is not None and not isinstance(value, (bool, int, float, str, list)):
            raise ValueError(f"{DEFAULTS_NAME}: {key} has unsupported type {type(value).__name__}")


def _read_yaml_mapping(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise RadfieldError(f"config file {path} not found") from None
    except (OSError, UnicodeDecodeError) as error:
        raise RadfieldError(f"config file {path} cannot be read: {error}") from error
    try:
        data = parse_yaml(text)
    except yaml.YAMLError as error:
        raise RadfieldError(f"{path}: not valid YAML: {yaml_problem(error)}") from error
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise RadfieldError(f"config file {path} must hold a mapping of keys, got {type(data).__name__}")
    return data
