"""The operand of a boolean entry: an analytic shape, a closed mesh or another field (placed by
rotate/translate/scale), with the ε of the field operand's boolean field B = [D > ε]."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radfield.errors import RadfieldError
from radfield.edit.boolean.masks import default_epsilon
from radfield.edit.boolean.shapes import Shape, mesh_shape, parse_shape
from radfield.edit.compose import transform_field
from radfield.edit.field import Field
from radfield.edit.model_operand import load_operand, same_kind
from radfield.edit.select import number, vector
from radfield.edit.warp import euler_rotation


@dataclass
class Operand:
    """A boolean's operand: a solid `shape` (analytic or mesh) or a field `other`, never both.
    epsilon: ε of the operand field's B (ε given, else its default) — for a shape, E's default;
    epsilon_e: ε of E's own B_E (the given ε, else E's default)."""
    shape: Shape | None
    other: Field | None
    epsilon: float
    epsilon_e: float


def read_operand(fld: Field, args, op: str, ctx) -> Operand:
    """The operand named by args (shape, mesh or model), checked against the operation `op`."""
    where = ctx.where
    other = None
    shape = None
    if "shape" in args:
        shape = parse_shape(args["shape"], f"{where}.shape")
    elif "mesh" in args:
        shape = mesh_shape(ctx.path(args["mesh"], "mesh"), f"{where}.mesh")
    if shape is not None and op in ("union", "xor"):
        raise RadfieldError(f"{where}.op: {op} needs a model operand (a shape has no radiance to add); use difference or intersection")
    if "model" in args:
        other = load_operand(args["model"], "model", ctx)
        same_kind(fld, other, where)
        if any(k in args for k in ("rotate", "translate", "scale")):
            rot = euler_rotation(vector(args, "rotate", where)) if "rotate" in args else np.eye(3)
            other = transform_field(other, rot, vector(args, "translate", where) if "translate" in args else np.zeros(3),
                                    number(args, "scale", where, default=1.0, positive=True))
    epsilon = number(args, "epsilon", where, default=default_epsilon(other.prims if other is not None else fld.prims), positive=True)
    epsilon_e = default_epsilon(fld.prims) if "epsilon" not in args else epsilon
    return Operand(shape, other, epsilon, epsilon_e)
