"""The pipeline configuration: defaults from `pipeline.yaml`, user overrides, validation.

`pipeline.yaml` is the file of defaults: every key a run can use, with its default value.
pipeline/schema.py is the schema: a dataclass per section, with each key's type, range or choices,
the flag that sets it and its docstring. `_defaults()` checks that the two name the same keys, in
the same order, and that every default fits its key.

A resolved config is a plain nested dict of YAML scalars and lists (`schema.typed(config)` is the
same config as a typed `Config`). Precedence, lowest first: `pipeline.yaml` < `--config FILE` <
`options` (the CLI's dedicated flags) < `--set key=value`.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import functools
import importlib.resources
import json
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from radfield.pipeline import schema
from radfield.pipeline.schema import Config, Key
from radfield.util.atomic import atomic_write_text
from radfield.util.yamlfile import parse_yaml, yaml_problem
from radfield.errors import RadfieldError

DEFAULTS_NAME = "pipeline.yaml"
COMMAND_LINE = "command line"   # the source of `options`: the CLI's own flags (schema.setting(flag=...))

_TYPE_NAMES = {bool: "a boolean", int: "an integer", float: "a number", str: "a string"}


def defaults_path() -> Path:
    """Where `pipeline.yaml` is: inside the `radfield` package (pyproject's package-data ships it)."""
    installed = Path(str(importlib.resources.files("radfield").joinpath(DEFAULTS_NAME)))
    if installed.is_file():
        return installed
    raise RadfieldError(f"{DEFAULTS_NAME} not found (looked at {installed})")


def load_defaults() -> dict[str, Any]:
    """The defaults as a fresh nested dict."""
    return copy.deepcopy(_defaults())


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
    """Set one dotted key of a resolved config in place, validated against the schema."""
    parts = key.split(".")
    node = config
    for depth, part in enumerate(parts[:-1], start=1):
        above = schema.find(".".join(parts[:depth]))
        if above is None:
            _unknown(key, source)
        if isinstance(above, Key):
            raise RadfieldError(f"{source}: config key {'.'.join(parts[:depth])} is a value, not a section")
        node = node[part]
    entry = schema.find(key)
    if entry is None:
        _unknown(key, source)
    if not isinstance(entry, Key):
        example = dataclasses.fields(entry)[0].name
        raise RadfieldError(f"{source}: config key {key} is a section; set the keys inside it, e.g. {key}.{example}")
    node[parts[-1]] = _checked(entry, value, source)


def section(config: Mapping[str, Any] | Config, keys: str | Iterable[str]) -> dict[str, Any]:
    """The part of `config` that a stage depends on (what its cache key hashes): a fresh plain copy
    holding only the given dotted keys, nested as in the full config. `config` is a typed `Config`
    (the pipeline's: the part is read off its dataclasses) or a nested mapping.

    `section(cfg, "train")` is `{"train": {...}}`; `section(cfg, ["train", "render", "seed"])` is
    `{"train": {...}, "render": {...}, "seed": 0}`; `section(cfg, "train.lr")` is
    `{"train": {"lr": {...}}}`. A key missing from `config` is a bug in a stage declaration
    (KeyError, or AttributeError for a `Config`).
    """
    out: dict[str, Any] = {}
    for key in [keys] if isinstance(keys, str) else keys:
        *parents, leaf = key.split(".")
        node: Any = config
        target = out
        for part in parents:
            node = _child(node, part)
            target = target.setdefault(part, {})
        target[leaf] = schema.plain(_child(node, leaf))
    return out


def save_resolved(config: Mapping[str, Any] | Config, path: Path) -> None:
    """Write the resolved config as YAML, atomically (a reader never sees half a file)."""
    atomic_write_text(Path(path), yaml.safe_dump(schema.plain(config), sort_keys=False, default_flow_style=None))


# --- validation -------------------------------------------------------------------------------

@functools.cache
def _defaults() -> dict[str, Any]:
    """The defaults, read and checked against the schema once per process (never mutate the result)."""
    defaults = _read_yaml_mapping(defaults_path())
    _check_defaults(defaults)
    return defaults


def value_at(config: Mapping[str, Any], key: str) -> Any:
    """The value of a dotted key in a nested config (KeyError when it has none)."""
    node: Any = config
    for part in key.split("."):
        node = node[part]
    return node


def _child(node: Any, name: str) -> Any:
    return node[name] if isinstance(node, Mapping) else getattr(node, name)


def _merge(config: dict[str, Any], partial: Mapping[str, Any], source: str, prefix: str = "") -> None:
    """Apply a partial nested mapping (a `--config` file) onto `config`, key by key."""
    for name, value in partial.items():
        key = f"{prefix}{name}"
        entry = schema.find(key)   # None: unknown, set_key reports it with a suggestion
        is_section = entry is not None and not isinstance(entry, Key)
        if is_section and value is None:
            continue  # `train:` with every key commented out overrides nothing
        if is_section and isinstance(value, dict):
            _merge(config, value, source, prefix=f"{key}.")
        else:
            set_key(config, key, value, source)


def _checked(key: Key, value: Any, source: str) -> Any:
    """`value` if it fits the key's type (ints widened to float), length, choices and range (each
    item of a list), else RadfieldError."""
    name = key.name
    if value is None:
        if key.nullable:
            return None
        raise _bad(source, key, describe(key), value)
    if key.is_list:
        if not isinstance(value, list) or (key.length is not None and len(value) != key.length):
            raise _bad(source, key, describe(key), value)
        items = [_checked_scalar(key, item, source, whole=value) for item in value]
        if key.selection:
            _check_selection(name, items, value_at(_defaults(), name), source)
        return items
    checked = _checked_scalar(key, value, source, whole=value)
    choices = key.choices() if callable(key.choices) else key.choices   # callable: read when checked
    if choices is not None and checked not in choices:
        raise _bad(source, key, f"one of {', '.join(choices)}", value)
    return checked


def _checked_scalar(key: Key, value: Any, source: str, whole: Any) -> Any:
    # bool is a subclass of int in Python; a config never means True when it says 1.
    if isinstance(value, bool) != (key.type is bool):
        ok = False
    elif key.type is float:
        ok = isinstance(value, (int, float))
    else:
        ok = isinstance(value, key.type)
    if not ok:
        raise _bad(source, key, describe(key), whole)
    if key.range is not None and not key.range.holds(value):
        what = key.range.describe()
        raise _bad(source, key, f"{'numbers ' if isinstance(whole, list) else ''}{what}", whole)
    return float(value) if key.type is float else value


def _bad(source: str, key: Key, what: str, value: Any) -> RadfieldError:
    """The one error line of a value that does not fit: a flag's names the flag the user typed,
    any other's the source and the key."""
    if source == COMMAND_LINE and key.flag is not None:
        return RadfieldError(f"{key.flag} must be {what}, got {_show(value)}")
    return RadfieldError(f"{source}: config key {key.name} must be {what}, got {_show(value)}")


def _check_selection(name: str, items: list[Any], default: list[Any], source: str) -> None:
    for item in items:
        if item not in default:
            close = difflib.get_close_matches(item, default, n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise RadfieldError(f"{source}: config key {name}: unknown entry {_show(item)}{hint}; "
                                f"choose from {', '.join(default)}")
    if len(set(items)) != len(items):
        raise RadfieldError(f"{source}: config key {name} lists an entry twice: {_show(items)}")


def _show(value: Any) -> str:
    """A value as the user wrote it in YAML/JSON (true, not True)."""
    return json.dumps(value, default=str)


def describe(key: Key) -> str:
    """What a key takes, as its error lines say it: "an integer", "an integer or null", "a list of 3 numbers"."""
    if key.is_list:
        length = "" if key.length is None else f"{key.length} "
        return f"a list of {length}{_TYPE_NAMES[key.type].split(' ', 1)[1]}s"
    return f"{_TYPE_NAMES[key.type]}{' or null' if key.nullable else ''}"


def _unknown(key: str, source: str) -> None:
    """Raise the unknown-key error, with the closest valid key as a suggestion."""
    close = difflib.get_close_matches(key, schema.names(), n=1, cutoff=0.6)
    hint = f" (did you mean {close[0]}?)" if close else ""
    raise RadfieldError(f"{source}: unknown config key {key}{hint}")


def _names(config: Mapping[str, Any], prefix: str = "") -> Iterable[str]:
    for name, value in config.items():
        yield f"{prefix}{name}"
        if isinstance(value, dict):
            yield from _names(value, prefix=f"{prefix}{name}.")


def _check_defaults(defaults: Mapping[str, Any]) -> None:
    """Catch a `pipeline.yaml` that disagrees with pipeline/schema.py (a bug, not a user error):
    other keys, another order, or a default of another type (an int where the schema says float)
    or out of its range."""
    if list(_names(defaults)) != schema.names():
        ours, theirs = set(_names(defaults)), set(schema.names())
        raise ValueError(f"{DEFAULTS_NAME} and pipeline/schema.py disagree: only in {DEFAULTS_NAME}: "
                         f"{sorted(ours - theirs)}, only in the schema: {sorted(theirs - ours)} (or the order)")
    for name, key in schema.keys().items():
        default = value_at(defaults, name)
        if not all(item is None or type(item) is key.type for item in (default if key.is_list else [default])):
            raise ValueError(f"{DEFAULTS_NAME}: {name} must be {describe(key)} (pipeline/schema.py), got {_show(default)}")
        # a registry's choices import it (torch): checked when a value is set; a selection selects from the default
        plain_key = dataclasses.replace(key, choices=None if callable(key.choices) else key.choices, selection=False)
        try:
            _checked(plain_key, default, DEFAULTS_NAME)
        except RadfieldError as error:
            raise ValueError(str(error)) from None


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
