"""Solid operands of a boolean: analytic shapes (sphere, box, half-space) by their signed distance,
and closed meshes by their generalised winding number."""

from __future__ import annotations

import contextlib
import io
import math
from collections.abc import Mapping

import numpy as np

from radfield.errors import RadfieldError
from radfield.edit.select import number, vector
from radfield.edit.spec import check_keys
from radfield.edit.warp import euler_rotation


class Shape:
    """An analytic solid: signed distance sd(x) (negative inside, 1-Lipschitz) and inside(x)."""

    def __init__(self, kind: str, sd, exact_extent=None):
        self.kind, self.sd, self.exact_extent = kind, sd, exact_extent
        self.mesh = None   # (vertices, triangles) of a mesh operand

    def inside(self, points: np.ndarray) -> np.ndarray:
        return self.sd(points) <= 0


def parse_shape(spec, where: str) -> Shape:
    if not isinstance(spec, Mapping) or len(spec) != 1:
        raise RadfieldError(f"{where}: a shape is one of {{sphere: ...}}, {{box: ...}}, {{halfspace: ...}}, got {spec!r}")
    (kind, args), = spec.items()
    w = f"{where}.{kind}"
    if not isinstance(args, Mapping):
        raise RadfieldError(f"{w}: expected a mapping of its parameters, got {args!r}")
    if kind == "sphere":
        check_keys(args, {"center", "radius"}, w)
        c, r = vector(args, "center", w), number(args, "radius", w, positive=True)
        return Shape("sphere", lambda p: np.linalg.norm(p - c, axis=1) - r)
    if kind == "halfspace":
        check_keys(args, {"point", "normal"}, w)
        point, normal = vector(args, "point", w), vector(args, "normal", w)
        if np.linalg.norm(normal) == 0:
            raise RadfieldError(f"{w}.normal: must not be zero")
        n = normal / np.linalg.norm(normal)
        # inside = the side the normal points to; an ellipsoid's extent along n is |S Rᵀ n| (exact)
        return Shape("halfspace", lambda p: -(p - point) @ n, exact_extent=n)
    if kind == "box":
        if "min" in args or "max" in args:
            check_keys(args, {"min", "max"}, w)
            lo, hi = vector(args, "min", w), vector(args, "max", w)
            if not (lo < hi).all():
                raise RadfieldError(f"{w}: min must be below max on every axis, got {lo.tolist()} and {hi.tolist()}")
            centre, half, rot = (lo + hi) / 2, (hi - lo) / 2, np.eye(3)
        else:
            check_keys(args, {"center", "size", "rotate"}, w)
            centre, size = vector(args, "center", w), vector(args, "size", w)
            if not (size > 0).all():
                raise RadfieldError(f"{w}.size: must be positive on every axis, got {size.tolist()}")
            half = size / 2
            rot = euler_rotation(vector(args, "rotate", w)) if "rotate" in args else np.eye(3)

        def sd(p):
            q = np.abs((p - centre) @ rot) - half
            return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)
        return Shape("box", sd)
    raise RadfieldError(f"{where}: unknown shape {kind!r} (expected sphere, box, halfspace)")


def read_mesh(path, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and triangles (F, 3) of a closed PLY / OBJ / STL mesh."""
    import meshio

    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            mesh = meshio.read(path)
    except (Exception, SystemExit) as exc:  # meshio raises many types (and may exit) on bad files
        raise RadfieldError(f"{where}: {path} is not a readable mesh ({type(exc).__name__})") from None
    tris = [c.data for c in mesh.cells if c.type == "triangle"]
    quads = [c.data for c in mesh.cells if c.type == "quad"]
    faces = tris + [q[:, [0, 1, 2]] for q in quads] + [q[:, [0, 2, 3]] for q in quads]
    if not faces:
        raise RadfieldError(f"{where}: {path} has no triangles")
    return np.asarray(mesh.points, np.float64)[:, :3], np.concatenate(faces).astype(np.int64)


def winding_number(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """Generalised winding number (Jacobson et al. 2013): Σ solid angles / 4π of the triangles seen
    from each point (van Oosterom-Strackee); ≈ 1 inside a closed mesh, 0 outside, robust to small holes."""
    tri = vertices[faces]                                              # (F, 3, 3)
    out = np.zeros(len(points))
    for lo in range(0, len(points), chunk):
        a, b, c = (tri[None, :, k] - points[lo:lo + chunk, None] for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
        out[lo:lo + chunk] = 2 * np.arctan2(det, den).sum(1) / (4 * math.pi)
    return out


def mesh_shape(path, where: str) -> Shape:
    v, f = read_mesh(path, where)
    lo, hi = v.min(0), v.max(0)

    def inside(p):
        out = np.zeros(len(p), bool)
        near = np.all((p >= lo) & (p <= hi), axis=1)   # nothing outside the bounding box is inside
        if near.any():
            out[near] = np.abs(winding_number(v, f, p[near])) > 0.5
        return out
    shape = Shape("mesh", None)
    shape.inside = inside
    shape.mesh = (v, f)
    return shape
