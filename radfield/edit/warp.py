"""Spec operations that move the cage: transform, deform (from a cage file), twist, bend, taper.

Each moves the selected cage vertices x (weight w from the selection and its falloff) to
x + w·(φ(x) − x) for its map φ (formulas below and in docs/usage.md, "The spec"), then deforms the
field exactly (edit/affine.py). Coordinates are the dataset's world frame; angles in degrees.

    transform  φ(x) = o + M·s·R·(x − o) + t,  R = Rz(rz)·Ry(ry)·Rx(rx)   (o: origin, default 0;
               M: `matrix`, 3 rows of 3, default I)
    twist      φ(x) = o + R_a(k·h)(x − o),  h = (x − o)·a
    bend       φ(x) = c + R_a(k·h)(x − h·e − c),  h = (x − o)·e, c = o + (a × e)/k  (identity for k = 0)
    taper      φ(x) = o + h·a + (1 + f·h)(x − o − h·a),  h = (x − o)·a
a: the unit axis (x, y, z or a vector), k: degrees_per_unit in radians per unit, e: bend's `along`
axis (default z, or x when the axis is z), f: taper's factor per unit.

A field without a cage takes `transform` with `select: all` (no falloff): its primitives are
mapped directly by the one affine map.

Each map comes with its Jacobian J = ∂φ/∂x in closed form (K: the cross-product matrix of a,
R = R_a(k·h), dR/dθ = K R):

    transform  J = M·s·R
    twist      J = R + k·(K R (x − o)) aᵀ
    bend       J = R (I − e eᵀ) + k·(K R y) eᵀ,  y = x − h·e − c
    taper      J = a aᵀ + (1 + f·h)(I − a aᵀ) + f·p aᵀ,  p = x − o − h·a
and with a selection's weight w: φ_w(x) = x + w(x)(φ(x) − x), J_w = I + w (J − I) + (φ(x) − x) ∇wᵀ
(w = smoothstep(1 − d/f) outside the region, ∇w = −6 t (1 − t) ∇d / f, t = 1 − d/f). With
`gradient: map` (these operations' default) every primitive takes μ' = φ_w(μ), A = J_w(μ)
(affine.map_field); a hard selection (no falloff, not `all`) makes φ_w jump at the region's
border, so there the default is the cage's interpolation instead ("smooth").
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from radfield.core.geometry.cage import read_cage
from radfield.errors import RadfieldError
from radfield.edit import affine
from radfield.edit.field import Field
from radfield.edit.select import number, signed_distance, vector, weights
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


def _options(args: Mapping, ctx: EditContext, where: str, closed_form: bool = False, continuous: bool = True) -> dict:
    """The operation's gradient, split and preserve_opacity (its own keys, else the command's flags).
    An operation with a closed-form map defaults to "map" where its weighted map is continuous,
    every other case to the cage's default (affine.DEFAULT_GRADIENT)."""
    gradient = args.get("gradient", ctx.options.get("gradient"))
    if gradient is None:
        gradient = affine.DEFAULT_MAP_GRADIENT if closed_form and continuous else affine.DEFAULT_GRADIENT
    if gradient not in affine.GRADIENTS:
        raise RadfieldError(f"{where}.gradient: one of {', '.join(affine.GRADIENTS)}, got {gradient!r}")
    if gradient == "map" and not closed_form:
        raise RadfieldError(f"{where}.gradient: map needs an operation's own map (transform, twist, bend, taper); "
                            f"a cage file takes {', '.join(affine.CAGE_GRADIENTS)}")
    if gradient == "map" and not continuous:
        raise RadfieldError(f"{where}.gradient: map needs a continuous map: 'select: all' or a falloff > 0 "
                            f"(a hard selection's map jumps at its border; the cage's {affine.DEFAULT_GRADIENT} interpolation blends it)")
    split = args.get("split", ctx.options.get("split", affine.SPLIT_THRESHOLD))
    if split is not False and split is not None:
        split = number({"split": split}, "split", where, positive=True)
    else:
        split = None
    preserve = args.get("preserve_opacity", ctx.options.get("preserve_opacity"))   # None: auto (edit/affine.py)
    if preserve is not None and not isinstance(preserve, bool):
        raise RadfieldError(f"{where}.preserve_opacity: expected true or false, got {preserve!r}")
    return {"gradient": gradient, "split": split, "preserve_opacity": preserve}


def _distance_gradient(selection, points: np.ndarray, where: str) -> np.ndarray:
    """∇d (N, 3) of the selection's signed distance outside its region (where the falloff acts)."""
    p = np.asarray(points, np.float64)
    (shape, args), = selection.items()
    if shape == "sphere":
        r = p - vector(args, "center", f"{where}.sphere")
        return r / np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-300)
    if shape == "plane":
        n = vector(args, "normal", f"{where}.plane")
        return np.broadcast_to(-n / np.linalg.norm(n), p.shape).copy()
    lo, hi = vector(args, "min", f"{where}.box"), vector(args, "max", f"{where}.box")
    r = p - (lo + hi) / 2
    q = np.maximum(np.abs(r) - (hi - lo) / 2, 0.0)         # outside: d = |q|, ∂d/∂x = sign(r) q / |q|
    return np.sign(r) * q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-300)


def weighted_map(phi, jacobian, selection, falloff: float, where: str):
    """φ_w(x) = x + w(x)(φ(x) − x) and its Jacobian J_w = I + w (J − I) + (φ(x) − x) ∇wᵀ (module
    docstring); w = 1 for `all`. Only called with a continuous weight (all, or falloff > 0)."""
    def w_and_grad(x):
        if selection in ("all", None):
            return np.ones(len(x)), np.zeros_like(x)
        d = signed_distance(selection, x, where)
        w = weights(selection, x, falloff, where)
        t = 1.0 - np.maximum(d, 0.0) / falloff
        slope = np.where((d > 0) & (t > 0), 6.0 * t * (1.0 - t) / falloff, 0.0)   # dw/dd = −slope
        return w, -slope[:, None] * _distance_gradient(selection, x, where)

    def phi_w(x):
        w, _ = w_and_grad(x)
        return x + w[:, None] * (phi(x) - x)

    def jac_w(x):
        w, grad_w = w_and_grad(x)
        return np.eye(3) + w[:, None, None] * (jacobian(x) - np.eye(3)) + np.einsum("ni,nj->nij", phi(x) - x, grad_w)

    return phi_w, jac_w


def _move_cage(fld: Field, args: Mapping, ctx: EditContext, phi, jacobian=None) -> Field:
    """Move the selected cage vertices by the map phi ((V, 3) -> (V, 3)) and deform the field: by
    the closed-form map and its `jacobian` at every primitive ("map"), or through the cage."""
    where = ctx.where
    if not fld.has_cage:
        raise RadfieldError(f"{where}: this field has no cage (only 'transform' with 'select: all' works without one)")
    falloff = number(args, "falloff", where, default=0.0)
    select = args.get("select", "all")
    w = weights(select, fld.cage_vertices, falloff, f"{where}.select")
    if not w.any():
        raise RadfieldError(f"{where}.select: selects no cage vertex")
    options = _options(args, ctx, where, closed_form=jacobian is not None,
                       continuous=select in ("all", None) or falloff > 0)
    if options["gradient"] == "map":
        phi_w, jac_w = weighted_map(phi, jacobian, select, falloff, f"{where}.select")
        out, inverted = affine.map_field(fld, phi_w, jac_w, split=options["split"],
                                         preserve_opacity=options["preserve_opacity"], where=where)
        if inverted:
            ctx.log(f"{where}: warning: the map flattened or turned {inverted} cage tets inside out (the field follows the map itself); "
                    f"cage-based edits and animations of the result are refused until it gets a new cage (--cage)")
        return out
    x = fld.cage_vertices
    new = x + w[:, None] * (phi(x) - x)
    return affine.deform_field(fld, new, where=where, **options)


@operation("transform")
def transform(fld: Field, args: Mapping, ctx: EditContext) -> Field:
    where = ctx.where
    check_keys(args, COMMON | {"rotate", "translate", "scale", "origin", "matrix"}, where)
    rot = euler_rotation(vector(args, "rotate", where)) if "rotate" in args else np.eye(3)
    t = vector(args, "translate", where) if "translate" in args else np.zeros(3)
    s = number(args, "scale", where, default=1.0, positive=True)
    o = vector(args, "origin", where) if "origin" in args else np.zeros(3)
    a = s * rot
    if "matrix" in args:   # a general linear part (shear, unequal scales), applied after s·R
        value = args["matrix"]
        rows_ok = isinstance(value, list) and len(value) == 3 and all(isinstance(r, list) and len(r) == 3 for r in value)
        flat = [x for row in value for x in row] if rows_ok else []
        if not rows_ok or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in flat) \
                or not np.isfinite(flat).all():
            raise RadfieldError(f"{where}.matrix: expected 3 rows of 3 numbers, got {value!r}")
        m = np.array(flat, np.float64).reshape(3, 3)
        if not np.linalg.det(m) > 0:
            raise RadfieldError(f"{where}.matrix: must keep orientation (determinant > 0), got {np.linalg.det(m):.4g}")
        a = m @ a
    select, falloff = args.get("select", "all"), args.get("falloff", 0)
    if select in ("all", None) and not falloff:
        # the whole field by one affine map: exact, and the only form a cage-less field takes
        out = affine.affine_field(fld, a, o + t - a @ o,
                                  preserve_opacity=_options(args, ctx, where, closed_form=True)["preserve_opacity"])
        out.notes.append({"operation": where.rsplit(".", 1)[-1], "entry": where, "split": 0,
                          "primitives": len(out.prims), "moved_primitives": len(out.prims)})
        return out
    return _move_cage(fld, args, ctx, *affine_map(a, o + t - a @ o))


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
    return affine.deform_field(fld, vertices, where=where, **_options(args, ctx, where))


def _axis_args(args: Mapping, where: str, rate_key: str):
    axis = parse_axis(args, "axis", where, default="z")
    origin = vector(args, "origin", where) if "origin" in args else np.zeros(3)
    rate = number(args, rate_key, where)
    return axis, origin, rate


def twist_map(axis: np.ndarray, origin: np.ndarray, k: float):
    """(φ, J) of the twist: k radians per unit of height about the unit axis through origin."""
    o = np.asarray(origin, np.float64)

    def phi(x):
        h = (x - o) @ axis
        return o + np.einsum("nij,nj->ni", axis_rotation(axis, k * h), x - o)

    def jacobian(x):
        h = (x - o) @ axis
        rot = axis_rotation(axis, k * h)
        rx = np.einsum("nij,nj->ni", rot, x - o)                             # R (x − o)
        return rot + k * np.einsum("ni,j->nij", np.cross(axis, rx), axis)    # R + k (K R (x − o)) aᵀ

    return phi, jacobian


def bend_map(axis: np.ndarray, origin: np.ndarray, along: np.ndarray, k: float):
    """(φ, J) of the bend about `axis` of the line origin + h·along (unit, perpendicular), k ≠ 0."""
    o = np.asarray(origin, np.float64)
    centre = o + np.cross(axis, along) / k

    def phi(x):
        h = (x - o) @ along
        return centre + np.einsum("nij,nj->ni", axis_rotation(axis, k * h), x - h[:, None] * along - centre)

    def jacobian(x):
        h = (x - o) @ along
        rot = axis_rotation(axis, k * h)
        ry = np.einsum("nij,nj->ni", rot, x - h[:, None] * along - centre)  # R y
        return rot @ (np.eye(3) - np.outer(along, along)) + k * np.einsum("ni,j->nij", np.cross(axis, ry), along)

    return phi, jacobian


def taper_map(axis: np.ndarray, origin: np.ndarray, f: float):
    """(φ, J) of the taper: the distance from the axis scaled by 1 + f·h."""
    o = np.asarray(origin, np.float64)
    aa = np.outer(axis, axis)

    def phi(x):
        h = (x - o) @ axis
        foot = o + h[:, None] * axis
        return foot + (1 + f * h)[:, None] * (x - foot)

    def jacobian(x):
        h = (x - o) @ axis
        perp = x - o - h[:, None] * axis
        return aa + (1 + f * h)[:, None, None] * (np.eye(3) - aa) + f * np.einsum("ni,j->nij", perp, axis)

    return phi, jacobian


def affine_map(a: np.ndarray, t: np.ndarray):
    """(φ, J) of x ↦ A x + t."""
    a, t = np.asarray(a, np.float64), np.asarray(t, np.float64)
    return (lambda x: x @ a.T + t), (lambda x: np.broadcast_to(a, (len(x), 3, 3)).copy())


@operation("twist")
def twist(fld: Field, args: Mapping, ctx: EditContext) -> Field:
    check_keys(args, COMMON | {"axis", "degrees_per_unit", "origin"}, ctx.where)
    axis, o, rate = _axis_args(args, ctx.where, "degrees_per_unit")
    return _move_cage(fld, args, ctx, *twist_map(axis, o, math.radians(rate)))


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
        return _move_cage(fld, args, ctx, *affine_map(np.eye(3), np.zeros(3)))
    return _move_cage(fld, args, ctx, *bend_map(axis, o, along, k))


@operation("taper")
def taper(fld: Field, args: Mapping, ctx: EditContext) -> Field:
    check_keys(args, COMMON | {"axis", "factor", "origin"}, ctx.where)
    axis, o, f = _axis_args(args, ctx.where, "factor")
    return _move_cage(fld, args, ctx, *taper_map(axis, o, f))
