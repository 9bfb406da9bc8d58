"""Deformed demo scenes, the ground truth of an edit (docs/usage.md "radfield demo-scene"): a
smooth map of the scene's shapes known in closed form, rendered by marching the deformed rays in
rest space (`demo-scene --deform twist|bend|squash`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from radfield.demo.raytrace import intersect
from radfield.demo.scenes import Scene
from radfield.errors import RadfieldError


MARCH_CAP = 0.05         # scene units: the longest sphere-tracing step (the Lipschitz bound holds over it)


MARCH_HIT = 1e-6         # a ray has hit when its point's rest-space distance to a shape is below this


MARCH_ITERATIONS = 4000  # a ray still undecided after this many steps grazes a surface: its last distance decides


def _rotation_z(angle: np.ndarray) -> np.ndarray:
    """Rotations (M, 3, 3) by angles (M,) radians about +z."""
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros((len(angle), 3, 3))
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1], out[:, 2, 2] = c, -s, s, c, 1.0
    return out


@dataclass(frozen=True)
class Deformation:
    """A smooth map φ of the scene (rest space x → deformed space y), known in closed form with its
    inverse and Jacobian, in the conventions of `radfield edit`'s operations (edit/warp.py), origin 0:

        twist   y = R_z(k·x_z) x                                   (k = degrees_per_unit, in radians)
        bend    about the y axis along z: the line x = y = 0 becomes an arc of radius 1/k, centre (1/k, 0, 0):
                y = (1/k + (x₁ − 1/k) cos θ, x₂, −(x₁ − 1/k) sin θ), θ = k·x₃
        squash  y = A x (`matrix`)

    A ray of the deformed scene is a curve in rest space; `intersect` marches along it (sphere
    tracing on the shapes' exact signed distances at φ⁻¹(y), each step shortened by a bound of
    |∂φ⁻¹/∂y| so that it never crosses a surface), except for the affine squash, whose rays stay
    straight and are intersected exactly in rest space."""

    kind: str
    degrees_per_unit: float = 0.0
    matrix: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

    @property
    def k(self) -> float:
        return math.radians(self.degrees_per_unit)

    def forward(self, x: np.ndarray) -> np.ndarray:
        """φ(x) of rest points x (M, 3)."""
        if self.kind == "twist":
            return np.einsum("mij,mj->mi", _rotation_z(self.k * x[:, 2]), x)
        if self.kind == "bend":
            r, theta = 1.0 / self.k, self.k * x[:, 2]
            s = x[:, 0] - r
            return np.stack([r + s * np.cos(theta), x[:, 1], -s * np.sin(theta)], -1)
        return x @ np.asarray(self.matrix).T

    def inverse(self, y: np.ndarray) -> np.ndarray:
        """φ⁻¹(y) of deformed points y (M, 3)."""
        if self.kind == "twist":
            return np.einsum("mij,mj->mi", _rotation_z(-self.k * y[:, 2]), y)
        if self.kind == "bend":
            r = 1.0 / self.k
            rho = np.hypot(y[:, 0] - r, y[:, 2])
            theta = np.arctan2(y[:, 2], r - y[:, 0])
            return np.stack([r - rho, y[:, 1], theta / self.k], -1)
        return np.linalg.solve(np.asarray(self.matrix), y.T).T

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """∂φ/∂x (M, 3, 3) at rest points x (M, 3)."""
        if self.kind == "twist":
            rot = _rotation_z(self.k * x[:, 2])
            rx = np.einsum("mij,mj->mi", rot, x)
            jac = rot.copy()
            jac[:, 0, 2] += -self.k * rx[:, 1]      # ∂(R x)/∂x₃ = k (ẑ × R x)
            jac[:, 1, 2] += self.k * rx[:, 0]
            return jac
        if self.kind == "bend":
            theta = self.k * x[:, 2]
            s = x[:, 0] - 1.0 / self.k
            jac = np.zeros((len(x), 3, 3))
            jac[:, 0, 0], jac[:, 0, 2] = np.cos(theta), -s * self.k * np.sin(theta)
            jac[:, 1, 1] = 1.0
            jac[:, 2, 0], jac[:, 2, 2] = -np.sin(theta), -s * self.k * np.cos(theta)
            return jac
        return np.broadcast_to(np.asarray(self.matrix, float), (len(x), 3, 3)).copy()

    def inverse_lipschitz(self, y: np.ndarray, radius: float) -> np.ndarray:
        """An upper bound (M,) of |∂φ⁻¹/∂y|₂ over the balls of `radius` around deformed points y:
        twist 1 + k·(distance from the axis) (the inverse twist's shear), bend 1/(k·ρ) across the
        arc (ρ the distance from the bend's centre line; 1 along the other directions), squash
        |A⁻¹|₂."""
        if self.kind == "twist":
            return 1.0 + self.k * (np.hypot(y[:, 0], y[:, 1]) + radius)
        if self.kind == "bend":
            rho = np.hypot(y[:, 0] - 1.0 / self.k, y[:, 2]) - radius
            return np.maximum(1.0, 1.0 / (self.k * np.maximum(rho, 1e-9)))
        return np.full(len(y), np.linalg.norm(np.linalg.inv(np.asarray(self.matrix)), 2))

    def spec(self) -> dict:
        """The same map as one operation of a `radfield edit` spec (edit/warp.py)."""
        if self.kind == "twist":
            return {"twist": {"axis": "z", "degrees_per_unit": self.degrees_per_unit, "origin": [0.0, 0.0, 0.0]}}
        if self.kind == "bend":
            return {"bend": {"axis": "y", "along": "z", "degrees_per_unit": self.degrees_per_unit,
                             "origin": [0.0, 0.0, 0.0]}}
        return {"transform": {"matrix": [list(row) for row in self.matrix]}}

    def intersect(self, scene: Scene, o: np.ndarray, d: np.ndarray):
        """First hit of the deformed scene's rays from o (3,) along unit d (R, 3): distance (R,) (inf
        on a miss), deformed unit normal (R, 3) (the rest normal mapped by J⁻ᵀ), index of the shape
        hit (R,) (-1 on a miss) and the hit's rest-space point (R, 3) (its material)."""
        o = np.asarray(o, np.float64)
        if self.kind == "squash":
            return self._intersect_affine(scene, o, d)
        return self.march(scene, o, d)

    def march(self, scene: Scene, o: np.ndarray, d: np.ndarray):
        """`intersect` by sphere tracing, for any kind (the tests check it against the exact affine
        path and the undeformed scene)."""
        o = np.asarray(o, np.float64)
        t = np.full(len(d), np.inf)
        index = np.full(len(d), -1)
        rest = np.zeros_like(d)
        # only the part of each ray inside the deformed scene's bounding ball is marched
        radius = self._bound(scene)
        b = d @ o
        disc = b * b - o @ o + radius**2
        live = np.flatnonzero(disc > 0)
        t_now = np.maximum(-b[live] - np.sqrt(disc[live]), 0.0)
        t_end = -b[live] + np.sqrt(disc[live])
        for _ in range(MARCH_ITERATIONS):
            if live.size == 0:
                break
            y = o + t_now[:, None] * d[live]
            x = self.inverse(y)
            dist = np.stack([p.sdf(x) for p in scene.primitives], 1)
            nearest, which = dist.min(1), dist.argmin(1)
            hit = nearest < MARCH_HIT
            t[live[hit]], index[live[hit]], rest[live[hit]] = t_now[hit], which[hit], x[hit]
            step = np.minimum(nearest / self.inverse_lipschitz(y, MARCH_CAP), MARCH_CAP)
            t_now = t_now + step
            go = ~hit & (t_now <= t_end)
            live, t_now, t_end = live[go], t_now[go], t_end[go]
        else:
            # grazing rays still undecided: within 1e-4 of a surface (~0.005 px at 128×128) is a hit
            y = o + t_now[:, None] * d[live]
            x = self.inverse(y)
            dist = np.stack([p.sdf(x) for p in scene.primitives], 1)
            hit = dist.min(1) < 1e-4
            t[live[hit]], index[live[hit]], rest[live[hit]] = t_now[hit], dist.argmin(1)[hit], x[hit]
        normal = np.zeros_like(d)
        rows = np.flatnonzero(index >= 0)
        if rows.size:
            normal[rows] = self._normals(scene, rest[rows], index[rows])
        return t, normal, index, rest

    def _intersect_affine(self, scene: Scene, o: np.ndarray, d: np.ndarray):
        # y = A x maps straight rays to straight rays: intersect in rest space along A⁻¹d, exactly
        a_inv = np.linalg.inv(np.asarray(self.matrix, float))
        o_rest, d_rest = a_inv @ o, d @ a_inv.T
        length = np.linalg.norm(d_rest, axis=-1)
        d_rest = d_rest / length[:, None]
        t_rest, normal_rest, index = intersect(scene, o_rest, d_rest)
        hit = np.isfinite(t_rest)
        rest = o_rest + np.where(hit, t_rest, 0.0)[:, None] * d_rest
        normal = normal_rest @ a_inv                                   # rows of A⁻ᵀ n
        normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-300)
        return t_rest / length, normal, index, rest

    def _normals(self, scene: Scene, x: np.ndarray, index: np.ndarray) -> np.ndarray:
        """Deformed unit normals at rest points x of shapes `index`: J⁻ᵀ ∇sdf (central differences)."""
        grad = np.zeros_like(x)
        h = 1e-6
        for k, primitive in enumerate(scene.primitives):
            rows = index == k
            for axis in range(3):
                e = np.zeros(3)
                e[axis] = h
                grad[rows, axis] = (primitive.sdf(x[rows] + e) - primitive.sdf(x[rows] - e)) / (2 * h)
        normal = np.linalg.solve(np.swapaxes(self.jacobian(x), 1, 2), grad[..., None])[..., 0]
        return normal / np.linalg.norm(normal, axis=-1, keepdims=True)

    def _bound(self, scene: Scene) -> float:
        """Radius of a ball about the origin holding the deformed scene: the image of the rest
        scene's bounding ball (sampled densely, with a margin)."""
        rest = max(np.linalg.norm(c) + r for c, r in (p.bounding_sphere for p in scene.primitives))
        n = 20000
        k = np.arange(n) + 0.5
        z = 1 - 2 * k / n
        phi = k * math.pi * (3 - math.sqrt(5))
        sphere = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], -1)
        points = np.concatenate([sphere * rest * f for f in (0.25, 0.5, 0.75, 1.0)])
        return 1.05 * float(np.linalg.norm(self.forward(points), axis=-1).max()) + 0.01


# The squash: scales 1.2 / 0.9 / 0.8 with shears (det 0.864 > 0), the affine map.
SQUASH_MATRIX = ((1.2, 0.3, 0.0), (0.0, 0.9, 0.0), (0.0, 0.25, 0.8))


DEFORMATIONS: dict[str, Deformation] = {
    "twist": Deformation("twist", degrees_per_unit=45.0),
    "bend": Deformation("bend", degrees_per_unit=30.0),
    "squash": Deformation("squash", matrix=SQUASH_MATRIX),
}


def get_deformation(name: str) -> Deformation:
    if name not in DEFORMATIONS:
        raise RadfieldError(f"unknown deformation {name!r} (available: {', '.join(DEFORMATIONS)})")
    return DEFORMATIONS[name]
