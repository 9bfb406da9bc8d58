"""Spec operations that move the cage: transform, deform (from a cage file), twist, bend, taper.

Each moves the selected cage vertices x (weight w from the selection and its falloff) to
x + w·(φ(x) − x) for its map φ (formulas below and in docs/usage.md, "The spec"), then deforms the
field exactly (edit/deform.py). Coordinates are the dataset's world frame; angles in degrees.

    transform  φ(x) = o + s·R·(x − o) + t,  R = Rz(rz)·Ry(ry)·Rx(rx)   (o: origin, default 0)
    twist      φ(x) = o + R_a(k·h)(x − o),  h = (x − o)·a
    bend       φ(x) = c + R_a(k·h)(x − h·e − c),  h = (x − o)·e, c = o + (a × e)/k  (identity for k = 0)
    taper      φ(x) = o + h·a + (1 + f·h)(x − o − h·a),  h = (x − o)·a
a: the unit axis (x, y, z or a vector), k: degrees_per_unit in radians per unit, e: bend's `along`
axis (default z, or x when the axis is z), f: taper's factor per unit.

A field without a cage takes `transform` with `select: all` (no falloff): its primitives are
mapped directly by the one affine map.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from radfield.core.geometry.cage import read_cage
from radfield.errors import RadfieldError
from radfield.edit import deform
from radfield.edit.field import Field
from radfield.edit.select import number, vector, weights
from radfield.edit.spec import EditContext, check_keys, operation

COMMON = frozenset({"select", "falloff", "gradient", "split", "preserve_opacity"})
AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def euler_rotation(degrees) -> np.ndarray:
    """R = Rz(rz)·Ry(ry)·Rx(rx) (extrinsic X, then Y, then Z), angles in degrees."""
    rx, ry, rz = np.radians(np.asarray(degrees, np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    r_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    r_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    r_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return r_z @ r_y @ r_x


def axis_rotation(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotations (N, 3, 3) by angles (N,) radians about the unit axis (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def parse_axis(args: Mapping, key: str, where: str, default=None) -> np.ndarray:
    value = args.get(key, default)
    if isinstance(value, str) and value.lower() in AXES:
        return np.array(AXES[value.lower()])
    axis = vector({key: value}, key, where)
    norm = np.linalg.norm(axis)
    if norm == 0:
        raise RadfieldError(f"{where}.{key}: must not be zero")
    return axis / norm


def _options(args: Mapping, ctx: EditContext, where: str) -> dict:
    gradient = args.get("gradient", ctx.options.get("gradient", deform.DEFAULT_GRADIENT))
    if gradient not in deform.GRADIENTS:
        raise RadfieldError(f"{where}.gradient: one of {', '.join(deform.GRADIENTS)}, got {gradient!r}")
    split = args.get("split", ctx.options.get("split", deform.SPLIT_THRESHOLD))
    if split is not False and split is not None:
        split = number({"split": split}, "split", where, positive=True)
    else:
        split = None
    preserve = args.get("preserve_opacity", ctx.options.get("preserve_opacity", False))
    if not isinstance(preserve, bool):
        raise RadfieldError(f"{where}.preserve_opacity: expected true or false, got {preserve!r}")
    return {"gradient": gradient, "split": split, "preserve_opacity": preserve}


def _move_cage(fld: Field, args: Mapping, ctx: EditContext, phi) -> Field:
    """Move the selected cage vertices by the map phi ((V, 3) -> (V, 3)) and deform the field."""
    where = ctx.where
    if not fld.has_cage:
        raise RadfieldError(f"{where}: this field has no cage (only 'transform' with 'select: all' works without one)")
    falloff = number(args, "falloff", where, default=0.0)
    w = weights(args.get("select", "all"), fld.cage_vertices, falloff, f"{where}.select")
    if not w.any():
        raise RadfieldError(f"{where}.select: selects no cage vertex")
    x = fld.cage_vertices
    new = x + w[:, None] * (phi(x) - x)
    return deform.deform_field(fld, new, where=where, **_options(args, ctx, where))


@operation("transform")
def transform(fld: Field, args: Mapping, ctx: EditContext) -> Field:
    where = ctx.where
    check_keys(args, COMMON | {"rotate", "translate", "scale", "origin"}, where)
    rot = euler_rotation(vector(args, "rotate", where)) if "rotate" in args else np.eye(3)
    t = vector(args, "translate", where) if "translate" in args else np.zeros(3)
    s = number(args, "scale", where, default=1.0, positive=True)
    o = vector(args, "origin", where) if "origin" in args else np.zeros(3)
    a = s * rot
    select, falloff = args.get("select", "all"), args.get("falloff", 0)
    if select in ("all", None) and not falloff:
        # the whole field by one affine map: exact, and the only form a cage-less field takes
        out = deform.affine_field(fld, a, o + t - a @ o, preserve_opacity=_options(args, ctx, where)["preserve_opacity"])
        out.notes.append({"operation": where.rsplit(".", 1)[-1], "entry": where, "split": 0,
                          "primitives": len(out.prims), "moved_primitives": len(out.prims)})
        return out
    return _move_cage(fld, args, ctx, lambda x: o + (x - o) @ a.T + t)


@operation("deform")
def deform_from_cage(fld: Field, args: Mapping, ctx: EditContext) -> Field:
    where = ctx.where
    check_keys(args, (COMMON - {"select", "falloff"}) | {"cage"}, where)
    if not fld.has_cage:
        raise RadfieldError(f"{where}: this field has no cage to replace")
    path = ctx.path(args.get("cage"), "cage")
    vertices, tets = read_cage(path)
    if tets.shape != fld.cage_tets.shape or len(vertices) != len(fld.cage_vertices) or not np.array_equal(tets, fld.cage_tets):
        raise RadfieldError(f"{where}.cage: {path} has another topology ({len(vertices)} vertices, {len(tets)} tets) "
                            f"than the field's cage ({len(fld.cage_vertices)} vertices, {len(fld.cage_tets)} tets)")
    return deform.deform_field(fld, vertices, where=where, **_options(args, ctx, where))


def _axis_args(args: Mapping, where: str, rate_key: str):
    axis = parse_axis(args, "axis", where, default="z")
    origin = vector(args, "origin", where) if "origin" in args else np.zeros(3)
    rate = number(args, rate_key, where)
    return axis, origin, rate


@operation("twist")
def twist(fld: Field, args: Mapping, ctx: EditContext) -> Field:
    check_keys(args, COMMON | {"axis", "degrees_per_unit", "origin"}, ctx.where)
    axis, o, rate = _axis_args(args, ctx.where, "degrees_per_unit")
    k = math.radians(rate)

    def phi(x):
        h = (x - o) @ axis
        return o + np.einsum("nij,nj->ni", axis_rotation(axis, k * h), x - o)

    return _move_cage(fld, args, ctx, phi)


@operation("bend")
def bend(fld: Field, args: Mapping, ctx: EditContext) -> Field:
    check_keys(args, COMMON | {"axis", "degrees_per_unit", "origin", "along"}, ctx.where)
    axis, o, rate = _axis_args(args, ctx.where, "degrees_per_unit")
    along = parse_axis(args, "along", ctx.where, default="x" if abs(axis[2]) > 0.9 else "z")
    along = along - (along @ axis) * axis                       # the bend runs across the axis
    if np.linalg.norm(along) < 1e-9:
        raise RadfieldError(f"{ctx.where}.along: must not be parallel to the axis")
    along /= np.linalg.norm(along)
    k = math.radians(rate)
    if k == 0:
        return _move_cage(fld, args, ctx, lambda x: x)
    centre = o + np.cross(axis, along) / k

    def phi(x):
        h = (x - o) @ along
        return centre + np.einsum("nij,nj->ni", axis_rotation(axis, k * h), x - h[:, None] * along - centre)

    return _move_cage(fld, args, ctx, phi)


@operation("taper")
def taper(fld: Field, args: Mapping, ctx: EditContext) -> Field:
    check_keys(args, COMMON | {"axis", "factor", "origin"}, ctx.where)
    axis, o, f = _axis_args(args, ctx.where, "factor")

    def phi(x):
        h = (x - o) @ axis
        along = o + h[:, None] * axis
        return along + (1 + f * h)[:, None] * (x - along)

    return _move_cage(fld, args, ctx, phi)
