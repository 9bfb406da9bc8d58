"""Selections: which points an operation acts on, and how strongly (a weight in [0, 1]).

A selection is `all` or a mapping with one key:
    box:    {min: [x0, y0, z0], max: [x1, y1, z1]}
    sphere: {center: [x, y, z], radius: r}
    plane:  {point: [x, y, z], normal: [nx, ny, nz]}      (the side the normal points to)
An operation's optional `falloff: f` (world units) turns the hard inside/outside into a smooth
weight: 1 inside, smoothstep(1 - d / f) at distance d outside, 0 beyond f.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from radfield.errors import RadfieldError

SHAPES = ("box", "sphere", "plane")


def signed_distance(selection, points: np.ndarray, where: str = "select") -> np.ndarray:
    """Signed distance (N,) of points (N, 3) to the selection's region: negative inside (exact
    for sphere and plane, the box's exact Euclidean distance outside and -(distance to the
    nearest face) inside). `all` gives -inf everywhere."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if selection == "all" or selection is None:
        return np.full(len(p), -np.inf)
    if not isinstance(selection, Mapping) or len(selection) != 1:
        raise RadfieldError(f"{where}: a selection is 'all' or one of {{{', '.join(SHAPES)}: ...}}, got {selection!r}")
    (shape, args), = selection.items()
    if shape not in SHAPES:
        raise RadfieldError(f"{where}: unknown selection {shape!r} (expected all, {', '.join(SHAPES)})")
    if not isinstance(args, Mapping):
        raise RadfieldError(f"{where}.{shape}: expected a mapping of its parameters, got {args!r}")
    if shape == "sphere":
        center = vector(args, "center", f"{where}.sphere")
        radius = number(args, "radius", f"{where}.sphere", positive=True)
        return np.linalg.norm(p - center, axis=1) - radius
    if shape == "plane":
        point = vector(args, "point", f"{where}.plane")
        normal = vector(args, "normal", f"{where}.plane")
        norm = np.linalg.norm(normal)
        if norm == 0:
            raise RadfieldError(f"{where}.plane.normal: must not be zero")
        return -(p - point) @ (normal / norm)
    lo, hi = vector(args, "min", f"{where}.box"), vector(args, "max", f"{where}.box")
    if not (lo < hi).all():
        raise RadfieldError(f"{where}.box: min must be below max on every axis, got {lo.tolist()} and {hi.tolist()}")
    q = np.abs(p - (lo + hi) / 2) - (hi - lo) / 2
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    return outside + np.minimum(q.max(1), 0)


def weights(selection, points: np.ndarray, falloff: float = 0.0, where: str = "select") -> np.ndarray:
    """Weight (N,) in [0, 1] of each point: 1 inside the selection, a smoothstep over `falloff`
    outside it, 0 beyond."""
    d = signed_distance(selection, points, where)
    if falloff < 0:
        raise RadfieldError(f"{where}: falloff must be >= 0, got {falloff}")
    if falloff == 0:
        return (d <= 0).astype(np.float64)
    t = np.clip(1.0 - np.maximum(d, 0) / falloff, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def vector(args: Mapping, key: str, where: str, size: int = 3) -> np.ndarray:
    """args[key] as a float vector of `size` finite numbers, or a one-line error naming it."""
    value = args.get(key) if isinstance(args, Mapping) else None
    try:
        out = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        out = np.zeros(0)
    if out.shape != (size,) or not np.isfinite(out).all():
        raise RadfieldError(f"{where}.{key}: expected {size} numbers, got {value!r}")
    return out


def number(args: Mapping, key: str, where: str, default=None, positive: bool = False) -> float:
    """args[key] as a finite float (default when absent and a default is given)."""
    value = args.get(key, default) if isinstance(args, Mapping) else default
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise RadfieldError(f"{where}.{key}: expected a number, got {value!r}")
    if positive and value <= 0:
        raise RadfieldError(f"{where}.{key}: must be positive, got {value!r}")
    return float(value)
