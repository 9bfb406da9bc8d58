"""Second operands of an operation (`model: OTHER_RUN_OR_MODEL`): another field, loaded through
the CLI's run loader (EditContext.load_operand) or, as a library fallback, from a model file."""

from __future__ import annotations

from radfield.core import kinds
from radfield.errors import RadfieldError
from radfield.edit.field import Field, load_field


def load_operand(value, key: str, ctx) -> Field:
    """The field named by args[key] (a run or a model file), resolved against the spec's folder."""
    path = ctx.path(value, key)
    if ctx.load_operand is not None:
        return ctx.load_operand(path)
    if path.is_file():
        return load_field(path)
    raise RadfieldError(f"{ctx.where}.{key}: {path} is a folder; only the edit command knows run layouts, give a model file")


def same_kind(fld: Field, other: Field, where: str) -> None:
    """Refuse (one line) to combine primitives of two kinds (neural primitives with Gaussians), or
    two models of a kind that cannot be joined (its `check_combinable`: neural fields whose
    density windows differ)."""
    if fld.prims.kind != other.prims.kind:
        raise RadfieldError(f"{where}: cannot combine a {fld.prims.kind} model with a {other.prims.kind} model")
    kinds.of(fld.prims).check_combinable(fld.prims, other.prims, where)
