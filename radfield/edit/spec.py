"""The edit spec: a YAML file with a list `operations:` applied in order, and the registry of the
operations it may name.

    operations:
      - transform: {select: all, rotate: [0, 0, 90], translate: [0, 0, 0.1], scale: 1.0}
      - boolean: {op: difference, shape: {sphere: {center: [0, 0, 0], radius: 0.3}}}

Each entry is a mapping with exactly one key, the operation's name; its value holds the
operation's arguments. An operation module registers itself with `@operation("name")` (sugar for
`OPERATIONS.register(name, fn)`, the registry every extension point uses); the function
takes (field, args, ctx) and returns the edited field. Every mistake in a spec is a RadfieldError
whose message starts with the entry's place, e.g. `operations[1].transform.scale: ...`.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from radfield.errors import RadfieldError
from radfield.edit.field import Field
from radfield.util.registry import Registry
from radfield.util.yamlfile import parse_yaml, yaml_problem

# modules whose import registers operations (one per operation family)
OPERATION_MODULES: tuple[str, ...] = ("radfield.edit.warp", "radfield.edit.boolean", "radfield.edit.compose",
                                     "radfield.edit.recolor", "radfield.edit.remesh")


@dataclass
class EditContext:
    """What an operation may need beyond its arguments.

    base_dir: relative paths in the spec are relative to this folder (the spec file's);
    load_operand: path of another model or run -> Field (the CLI supplies it: it knows run layouts);
    device: torch device for operations that render or train; seed: their random seed;
    log: one-line progress messages; where: the entry's place in the spec, for error messages."""

    base_dir: Path = Path(".")
    load_operand: Callable[[Path], Field] | None = None
    device: str = "cpu"
    seed: int = 0
    log: Callable[[str], None] = lambda message: None
    where: str = "operations"
    options: dict[str, Any] = field(default_factory=dict)

    def path(self, value: Any, key: str) -> Path:
        """A path argument, resolved against base_dir, that must exist."""
        if not isinstance(value, (str, Path)) or not str(value):
            raise RadfieldError(f"{self.where}.{key}: expected a path, got {value!r}")
        path = Path(value).expanduser()
        path = path if path.is_absolute() else self.base_dir / path
        if not path.exists():
            raise RadfieldError(f"{self.where}.{key}: {path} does not exist")
        return path


Operation = Callable[[Field, Mapping[str, Any], EditContext], Field]
OPERATIONS: Registry[Operation] = Registry("edit operation")   # filled by OPERATION_MODULES' imports


def operation(name: str) -> Callable[[Operation], Operation]:
    """Decorator: register `fn` as the spec operation `name` (OPERATIONS.register(name, fn))."""

    def register(fn: Operation) -> Operation:
        return OPERATIONS.register(name, fn)

    return register


def registry() -> dict[str, Operation]:
    """Every operation a spec may name, {name: function}, once OPERATION_MODULES are imported."""
    for module in OPERATION_MODULES:
        importlib.import_module(module)
    return dict(OPERATIONS.items())


def read_spec(path: str | Path) -> list[tuple[str, dict]]:
    """The operations of a spec file as (name, args) pairs, checked for form (not for values)."""
    return parse_spec(read_yaml(path, "the edit spec"), str(path))


def read_yaml(path: str | Path, what: str = "the file") -> Any:
    """A YAML file's content, or a one-line error naming the file."""
    path = Path(path)
    try:
        # the pipeline config's loader: numbers as users write them (1e6), in one place
        return parse_yaml(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise RadfieldError(f"{path}: cannot read {what} ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise RadfieldError(f"{path}: not valid YAML: {yaml_problem(exc)}") from None


def parse_spec(data: Any, source: str = "spec") -> list[tuple[str, dict]]:
    if not isinstance(data, Mapping) or "operations" not in data:
        raise RadfieldError(f"{source}: an edit spec is a mapping with a list 'operations:'")
    unknown = sorted(set(data) - {"operations"})
    if unknown:
        raise RadfieldError(f"{source}: unknown top-level keys {unknown} (only 'operations' is allowed)")
    ops = data["operations"]
    if not isinstance(ops, list) or not ops:
        raise RadfieldError(f"{source}: 'operations' must be a non-empty list")
    known = registry()
    out = []
    for i, entry in enumerate(ops):
        where = f"{source}: operations[{i}]"
        if not isinstance(entry, Mapping) or len(entry) != 1:
            raise RadfieldError(f"{where}: each operation is a mapping with one key (its name), got {entry!r}")
        (name, args), = entry.items()
        if name not in known:
            raise RadfieldError(f"{where}: unknown operation {name!r} (known: {', '.join(sorted(known))})")
        if args is None:
            args = {}
        if not isinstance(args, Mapping):
            raise RadfieldError(f"{where}.{name}: expected a mapping of arguments, got {args!r}")
        out.append((str(name), dict(args)))
    return out


def apply_operations(fld: Field, operations: list[tuple[str, dict]], ctx: EditContext,
                     sources: list[str] | None = None) -> Field:
    """Apply (name, args) pairs in order; each operation's figures are appended to fld.notes.
    `sources`: where each operation was written (a spec file's path), which its errors name first."""
    known = registry()
    for i, (name, args) in enumerate(operations):
        source = sources[i] if sources is not None else None
        ctx.where = f"{source}: operations[{i}].{name}" if source else f"operations[{i}].{name}"
        fld = known[name](fld, args, ctx)
    return fld


def check_keys(args: Mapping[str, Any], allowed: set[str] | frozenset[str], where: str) -> None:
    """One-line error for argument names an operation does not take."""
    unknown = sorted(set(args) - set(allowed))
    if unknown:
        raise RadfieldError(f"{where}: unknown arguments {unknown} (allowed: {', '.join(sorted(allowed))})")
