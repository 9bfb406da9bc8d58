"""Second operands of an operation (`model: OTHER_RUN_OR_MODEL`): another field, loaded through
the CLI's run loader (EditContext.load_operand) or, as a library fallback, from a model file."""

from __future__ import annotations

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
    """Refuse (one line) to combine neural primitives with Gaussians, or neural fields whose
    density windows differ (`same_window`)."""
    if fld.prims.kind != other.prims.kind:
        raise RadfieldError(f"{where}: cannot combine a {fld.prims.kind} model with a {other.prims.kind} model")
    same_window(fld.prims, other.prims, where)


def same_window(a, b, where: str) -> None:
    """Refuse (one line) to combine primitives whose `window` differs: a model is drawn with one
    density, windowed 1.5 (1 − r²) σ or hard-edged σ, and converting one into the other would need
    a retraining (Gaussians have no window)."""
    wa, wb = getattr(a, "window", False), getattr(b, "window", False)
    if wa != wb:
        name = lambda w: "windowed" if w else "hard-edged"
        raise RadfieldError(f"{where}: cannot combine a {name(wa)} neural model (window={int(wa)}) with a "
                            f"{name(wb)} one (window={int(wb)}); a model has one density window")
