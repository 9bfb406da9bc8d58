"""Analytic shapes for the synthetic scenes: exact ray intersection (numpy, batched over rays),
procedural albedo, and a triangulation for the ground-truth mesh.

Every shape has a `bounding_sphere` (centre (3,), radius) for culling rays, `sdf(x)` (the exact
signed distance of points (M, 3), negative inside) and `intersect(o, d)`, which takes rays from origins o, one (3,) (a camera centre) or one per ray (R, 3) (shadow rays from
surface points), in unit directions d (R, 3) (float64) and returns the distance to the first hit
in front of the origin (R,) (inf on a miss) and the outward unit normal there (R, 3). The origin
is assumed outside every shape.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

_EPS = 1e-9


@dataclass(frozen=True)
class Material:
    """Albedo: 'solid' `colour`, a 3D 'checker' of cells 1/frequency wide, or 'stripes' across
    `axis` with period 1/frequency, alternating `colour` and `colour2`. `specular` > 0 adds a
    white Blinn-Phong highlight specular · max(0, n·h)^shininess (h the half vector between the
    light and the eye): view-dependent colour; 0 is Lambertian (view-independent)."""

    colour: tuple[float, float, float]
    pattern: str = "solid"
    colour2: tuple[float, float, float] = (1.0, 1.0, 1.0)
    frequency: float = 0.0
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    specular: float = 0.0
    shininess: float = 32.0

    def albedo(self, x: np.ndarray) -> np.ndarray:
        """Albedo (M, 3) at world points x (M, 3)."""
        if self.pattern == "solid":
            return np.broadcast_to(np.asarray(self.colour), x.shape).copy()
        if self.pattern == "checker":
            # Quarter-cell offset keeps axis-aligned faces at round coordinates off cell borders.
            second = np.floor(x * self.frequency + 0.25).sum(-1) % 2 == 1
        elif self.pattern == "stripes":
            second = np.floor(2 * self.frequency * (x @ np.asarray(self.axis)) + 0.25) % 2 == 1
        else:
            raise ValueError(f"unknown pattern {self.pattern!r}")
        return np.where(second[:, None], np.asarray(self.colour2), np.asarray(self.colour))


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of (R, 3) arrays (much faster than (a * b).sum(-1))."""
    return np.einsum("ij,ij->i", a, b)


def _miss(t: np.ndarray, hit: np.ndarray) -> np.ndarray:
    return np.where(hit, t, np.inf)


def _rows(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The origin of every ray (R, 3), from one origin (3,) or one per ray."""
    return np.broadcast_to(np.asarray(o, dtype=np.float64), d.shape)


def _box_distance(q: np.ndarray) -> np.ndarray:
    """Exact signed Euclidean distance to the box {|q_i| <= 0} from q = |x_local| − half-extents
    (M, k): what every shape's `sdf` reduces to. A ray marcher may step by an exact distance without
    crossing a surface (deformations.py, `Deformation`: the deformed demo scenes)."""
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)


@dataclass(frozen=True)
class Sphere:
    center: tuple[float, float, float]
    radius: float
    material: Material

    @property
    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        return np.asarray(self.center), self.radius

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        oc = _rows(o, d) - np.asarray(self.center)
        b = _dot(d, oc)
        disc = b * b - _dot(oc, oc) + self.radius**2
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        t = _miss(t, (disc >= 0) & (t > _EPS))
        hit_t = np.where(np.isfinite(t), t, 0.0)
        return t, (oc + hit_t[:, None] * d) / self.radius

    def sdf(self, x: np.ndarray) -> np.ndarray:
        """Exact signed distance (M,) of points x (M, 3), negative inside."""
        return np.linalg.norm(x - np.asarray(self.center), axis=-1) - self.radius

    def mesh(self):
        import pyvista as pv

        return pv.Sphere(radius=self.radius, center=self.center, theta_resolution=32, phi_resolution=16)


@dataclass(frozen=True)
class Box:
    """A box of half-extents `half_size`, turned by `yaw` degrees about the world z axis."""

    center: tuple[float, float, float]
    half_size: tuple[float, float, float]
    material: Material
    yaw: float = 0.0

    @property
    def rotation(self) -> np.ndarray:
        """Box-to-world rotation (3, 3)."""
        c, s = math.cos(math.radians(self.yaw)), math.sin(math.radians(self.yaw))
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    @property
    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        return np.asarray(self.center), float(np.linalg.norm(self.half_size))

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # Slab test in the box frame (row vectors: x @ R is R^T x).
        R, h = self.rotation, np.asarray(self.half_size)
        o_local, d_local = (_rows(o, d) - np.asarray(self.center)) @ R, d @ R  # (R, 3) each
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-h - o_local) / d_local, (h - o_local) / d_local
        t_min, t_max = np.minimum(t1, t2), np.maximum(t1, t2)
        t_near, t_far = t_min.max(-1), t_max.min(-1)
        t = _miss(t_near, (t_near <= t_far) & (t_near > _EPS))
        # The entry face is the slab entered last; its normal faces the incoming ray.
        axis = t_min.argmax(-1)
        normal = np.zeros_like(d)
        rows = np.arange(len(d))
        normal[rows, axis] = -np.sign(d_local[rows, axis])
        return t, normal @ R.T

    def sdf(self, x: np.ndarray) -> np.ndarray:
        local = (x - np.asarray(self.center)) @ self.rotation
        return _box_distance(np.abs(local) - np.asarray(self.half_size))

    def mesh(self):
        import pyvista as pv

        x, y, z = (2 * v for v in self.half_size)
        return pv.Cube(center=(0, 0, 0), x_length=x, y_length=y, z_length=z).rotate_z(self.yaw).translate(self.center)


@dataclass(frozen=True)
class Cylinder:
    """A capped cylinder (a rod) of `radius` from `start` to `end`."""

    start: tuple[float, float, float]
    end: tuple[float, float, float]
    radius: float
    material: Material

    @property
    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        a, b = np.asarray(self.start), np.asarray(self.end)
        return (a + b) / 2, math.hypot(np.linalg.norm(b - a) / 2, self.radius)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a, b = np.asarray(self.start), np.asarray(self.end)
        length = np.linalg.norm(b - a)
        u = (b - a) / length
        # Split origin and direction along the axis and across it.
        oa = _rows(o, d) - a
        o_z, d_z = oa @ u, d @ u
        o_p, d_p = oa - o_z[:, None] * u, d - d_z[:, None] * u
        qa, qb, qc = _dot(d_p, d_p), _dot(d_p, o_p), _dot(o_p, o_p) - self.radius**2
        disc = qb * qb - qa * qc
        # Rays parallel to the axis or to the caps divide by zero; those terms come out as misses.
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            t_side = (-qb - np.sqrt(np.maximum(disc, 0.0))) / qa
            z_side = o_z + t_side * d_z
            t_side = _miss(t_side, (disc >= 0) & (qa > 0) & (t_side > _EPS) & (z_side >= 0) & (z_side <= length))
            t_caps = []
            for z in (0.0, length):
                t_cap = (z - o_z) / d_z
                across = o_p + t_cap[:, None] * d_p
                t_caps.append(_miss(t_cap, (t_cap > _EPS) & (_dot(across, across) <= self.radius**2)))
        t = np.minimum(t_side, np.minimum(*t_caps))
        hit_t = np.where(np.isfinite(t), t, 0.0)
        side_normal = (o_p + hit_t[:, None] * d_p) / self.radius
        normal = np.where((t == t_side)[:, None], side_normal, np.where((t == t_caps[0])[:, None], -u, u))
        return t, normal

    def sdf(self, x: np.ndarray) -> np.ndarray:
        a, b = np.asarray(self.start), np.asarray(self.end)
        length = np.linalg.norm(b - a)
        u = (b - a) / length
        xa = x - a
        z = xa @ u
        radial = np.linalg.norm(xa - z[:, None] * u, axis=-1)
        # a 2D box in (radial, axial) coordinates
        return _box_distance(np.stack([radial - self.radius, np.abs(z - length / 2) - length / 2], -1))

    def mesh(self):
        import pyvista as pv

        a, b = np.asarray(self.start), np.asarray(self.end)
        return pv.Cylinder(
            center=(a + b) / 2, direction=b - a, radius=self.radius, height=np.linalg.norm(b - a), resolution=16
        )


@dataclass(frozen=True)
class Torus:
    """A torus (a ring, genus 1) around `axis` through `center`: the points at distance `minor`
    from the circle of radius `major` in the plane normal to `axis`."""

    center: tuple[float, float, float]
    axis: tuple[float, float, float]
    major: float
    minor: float
    material: Material

    @property
    def frame(self) -> np.ndarray:
        """Torus-to-world rotation (3, 3): its third column is the unit axis."""
        z = np.asarray(self.axis, float) / np.linalg.norm(self.axis)
        helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(helper, z)
        x /= np.linalg.norm(x)
        return np.stack([x, np.cross(z, x), z], 1)

    @property
    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        return np.asarray(self.center), self.major + self.minor

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # In the torus frame, p = o + t d satisfies (|p|^2 + R^2 - r^2)^2 = 4 R^2 (p_x^2 + p_y^2):
        # a quartic in t (|d| = 1), solved as the eigenvalues of its companion matrix.
        F = self.frame
        R, r = self.major, self.minor
        o_l, d_l = (_rows(o, d) - np.asarray(self.center)) @ F, d @ F
        b, k = _dot(d_l, o_l), _dot(o_l, o_l) + R * R - r * r
        c3 = 4 * b
        c2 = 4 * b * b + 2 * k - 4 * R * R * (d_l[:, 0] ** 2 + d_l[:, 1] ** 2)
        c1 = 4 * b * k - 8 * R * R * (o_l[:, 0] * d_l[:, 0] + o_l[:, 1] * d_l[:, 1])
        c0 = k * k - 4 * R * R * (o_l[:, 0] ** 2 + o_l[:, 1] ** 2)
        companion = np.zeros((len(d), 4, 4))
        companion[:, 0] = -np.stack([c3, c2, c1, c0], 1)
        companion[:, [1, 2, 3], [0, 1, 2]] = 1.0
        roots = np.linalg.eigvals(companion) if len(d) else np.zeros((0, 4), complex)
        real = np.abs(roots.imag) <= 1e-6 * np.maximum(1.0, np.abs(roots.real))
        t = np.where(real & (roots.real > _EPS), roots.real, np.inf).min(1)
        hit = np.isfinite(t)
        p = o_l + np.where(hit, t, 0.0)[:, None] * d_l
        ring = p.copy()
        ring[:, 2] = 0.0
        ring *= R / np.maximum(np.linalg.norm(ring, axis=1, keepdims=True), _EPS)  # nearest point of the core circle
        normal = (p - ring) / np.maximum(np.linalg.norm(p - ring, axis=1, keepdims=True), _EPS)
        return t, normal @ F.T

    def sdf(self, x: np.ndarray) -> np.ndarray:
        local = (x - np.asarray(self.center)) @ self.frame
        return np.hypot(np.hypot(local[:, 0], local[:, 1]) - self.major, local[:, 2]) - self.minor

    def mesh(self):
        import pyvista as pv

        torus = pv.ParametricTorus(ringradius=self.major, crosssectionradius=self.minor, u_res=48, v_res=24, w_res=0)
        matrix = np.eye(4)
        matrix[:3, :3], matrix[:3, 3] = self.frame, self.center
        return torus.transform(matrix, inplace=False)
