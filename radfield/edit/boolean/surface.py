"""Points on the operand's boundary inside a box, with outward normals, for every operand kind:
an analytic shape's zero level set, a mesh's triangles, a field's ε-level set of D."""

from __future__ import annotations

import numpy as np

from radfield.core.kinds import neural_density

from radfield.edit.boolean.shapes import Shape
from radfield.edit.field import Field


def cut_surface(shape: Shape | None, other: Field | None, epsilon: float, lo: np.ndarray, hi: np.ndarray,
                spacing: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Points about `spacing` apart on the operand's boundary inside [lo, hi] and the outward
    normals there, by the operand's kind: `shape` (analytic or mesh) or the field `other` at ε."""
    if shape is not None and shape.sd is not None:
        return surface_points(shape, lo, hi, spacing)
    if shape is not None:
        return mesh_surface_points(shape, lo, hi, spacing, seed)
    return level_set_points(other, epsilon, lo, hi, spacing)


def _thin(points: np.ndarray, normals: np.ndarray, spacing: float):
    """One point (and its normal) per cell of side `spacing`."""
    if len(points) == 0:
        return points, normals
    _, first = np.unique(np.floor(points / spacing).astype(np.int64), axis=0, return_index=True)
    first = np.sort(first)
    return points[first], normals[first]


def _in_box(points: np.ndarray, lo, hi) -> np.ndarray:
    return np.all((points >= lo) & (points <= hi), axis=1)


def surface_points(shape: Shape, lo: np.ndarray, hi: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points about `spacing` apart on an analytic shape's surface inside the box [lo, hi] and the
    outward normals there: a grid of the box projected onto the zero level set of the signed
    distance (Newton steps along its gradient)."""
    axes = [np.arange(a, b + spacing, spacing) for a, b in zip(lo, hi)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    grid = grid[np.abs(shape.sd(grid)) < spacing]
    for _ in range(4):
        g = _gradient(shape.sd, grid)
        grid = grid - shape.sd(grid)[:, None] * g
    grid = grid[np.abs(shape.sd(grid)) < 1e-3 * spacing]
    return _thin(grid, _gradient(shape.sd, grid), spacing)


def mesh_surface_points(shape: Shape, lo: np.ndarray, hi: np.ndarray, spacing: float, seed: int = 0):
    """Points about `spacing` apart on a mesh operand's triangles inside the box [lo, hi], and the
    outward normals there: area-weighted samples of the triangles that meet the box (about
    2·area/spacing² per triangle), thinned to one per cell; a triangle normal is flipped where a
    step along it enters the mesh (winding number), so a mesh whose triangles face inwards works too."""
    v, f = shape.mesh
    tri = v[f]                                                        # (F, 3, 3)
    meets = np.all((tri.max(1) >= lo) & (tri.min(1) <= hi), axis=1)
    tri = tri[meets]
    empty = np.zeros((0, 3))
    if len(tri) == 0:
        return empty, empty
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    keep = area > 0
    tri, cross, area = tri[keep], cross[keep], area[keep]
    count = 2 * area / spacing**2
    count = np.ceil(count * min(1.0, 1e6 / max(count.sum(), 1.0))).astype(np.int64)   # at most ~10⁶ samples
    owner = np.repeat(np.arange(len(tri)), count)
    rng = np.random.default_rng(seed)
    r1, r2 = np.sqrt(rng.random(len(owner))), rng.random(len(owner))   # uniform on a triangle
    points = ((1 - r1)[:, None] * tri[owner, 0] + (r1 * (1 - r2))[:, None] * tri[owner, 1]
              + (r1 * r2)[:, None] * tri[owner, 2])
    normals = cross[owner] / (2 * area[owner, None])
    inside = _in_box(points, lo, hi)
    points, normals = _thin(points[inside], normals[inside], spacing)
    if len(points):
        flip = shape.inside(points + 0.1 * spacing * normals)
        normals[flip] = -normals[flip]
    return points, normals


def level_set_points(fld: Field, epsilon: float, lo: np.ndarray, hi: np.ndarray, spacing: float,
                     max_points: int = 120_000):
    """Points about `spacing` apart on a field operand's boundary D = ε inside [lo, hi] and the
    outward normals −∇D/|∇D| there: D sampled on a grid (spacing/2, coarsened to at most max_points
    nodes), each grid edge whose ends lie on both sides of ε gives the linearly interpolated
    crossing, the normal from the grid's central-difference gradient at its nearer end."""
    h = spacing / 2
    while np.prod(np.ceil((hi - lo) / h) + 1) > max_points:
        h *= 1.25
    shape = (np.ceil((hi - lo) / h) + 1).astype(int)
    axes = [lo[i] + h * np.arange(shape[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    d = neural_density.field_density(fld.prims, grid.reshape(-1, 3)).reshape(shape)
    grad = np.stack(np.gradient(d, h), -1)
    points, normals = [], []
    for axis in range(3):
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[axis], b[axis] = slice(0, -1), slice(1, None)
        d0, d1 = d[tuple(a)], d[tuple(b)]
        cross = (d0 > epsilon) != (d1 > epsilon)
        if not cross.any():
            continue
        t = (epsilon - d0[cross]) / (d1[cross] - d0[cross])
        p0, p1 = grid[tuple(a)][cross], grid[tuple(b)][cross]
        g = np.where((t < 0.5)[:, None], grad[tuple(a)][cross], grad[tuple(b)][cross])
        points.append(p0 + t[:, None] * (p1 - p0))
        normals.append(-g)
    if not points:
        return np.zeros((0, 3)), np.zeros((0, 3))
    points, normals = np.concatenate(points), np.concatenate(normals)
    ok = np.linalg.norm(normals, axis=1) > 0
    normals = normals[ok] / np.linalg.norm(normals[ok], axis=1, keepdims=True)
    return _thin(points[ok], normals, spacing)


def _gradient(sd, p: np.ndarray, h: float = 1e-5) -> np.ndarray:
    g = np.stack([(sd(p + h * e) - sd(p - h * e)) / (2 * h) for e in np.eye(3)], -1)
    return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)
