"""Where a dataset's object is, as far as its files tell: the point its cameras converge on, the
dataset's own mesh (`mesh.ply`), and from them the object's bounds, which a point light of a
one-light-at-a-time capture must lie outside (datasets/transforms.py: check_light_bounds).

The bounds are the mesh's axis-aligned box when the dataset ships a mesh (exact: the mesh is the
object). Otherwise they come from the cameras of an object-centric capture, which all frame the
object: the ball about their focus point (the point nearest to every optical axis) of radius
min_k d_k sin(θ_k / 2), d_k camera k's distance to the focus and θ_k its narrower field of view,
i.e. the largest ball about the focus that every camera sees whole. A capture framed around its
object keeps the object about this size (the demo scenes: cameras at 4, θ = 0.69 rad, radius 1.35,
against 1.1 for the farthest point of the studio objects). Cameras without a common focus
(forward-facing rigs) say nothing about an object: no bounds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radfield.core.geometry.cameras import Camera
from radfield.errors import RadfieldError

MESH = "mesh.ply"  # a dataset's own mesh (our synthetic scenes ship one), used to initialise


@dataclass(frozen=True)
class Bounds:
    """An axis-aligned box (`low`, `high`) or a ball (`center`, `radius`), world units."""

    low: np.ndarray | None = None
    high: np.ndarray | None = None
    center: np.ndarray | None = None
    radius: float = 0.0

    def contains(self, point) -> bool:
        point = np.asarray(point, dtype=np.float64)
        if self.low is not None:
            return bool(np.all(point >= self.low) and np.all(point <= self.high))
        return bool(np.linalg.norm(point - self.center) < self.radius)

    def describe(self) -> str:
        """For messages: what the bounds are and where they came from."""
        if self.low is not None:
            return f"the box {_fmt(self.low)} .. {_fmt(self.high)} of the dataset's {MESH}"
        return (f"the ball of radius {self.radius:.3g} about {_fmt(self.center)} that every camera frames "
                "(their focus point)")


def object_bounds(cameras: list[Camera], mesh: Path) -> Bounds | None:
    """The object's bounds (see the module docstring): the box of `mesh` when that file exists,
    else the ball every camera frames about their focus point, else None."""
    if mesh.is_file():
        vertices = read_mesh(mesh)["mesh_vertices"].astype(np.float64)
        if len(vertices):
            return Bounds(low=vertices.min(0), high=vertices.max(0))
    focus = focus_point(cameras) if len(cameras) > 1 else None
    if focus is None:
        return None
    radius = min(float(np.linalg.norm(cam.center.numpy() - focus)) * math.sin(_half_fov(cam)) for cam in cameras)
    return Bounds(center=focus, radius=radius)


def _half_fov(camera: Camera) -> float:
    """Half the narrower field of view (radians), about the principal axis."""
    return math.atan(min(camera.width / (2 * camera.fx), camera.height / (2 * camera.fy)))


def _fmt(vector) -> str:
    return "[" + ", ".join(f"{x:.3g}" for x in vector) + "]"


def focus_point(cameras: list[Camera]) -> np.ndarray | None:
    """The point nearest to every optical axis in the least-squares sense, or None when the axes
    are close to parallel (forward-facing rigs) or the point is not in front of the cameras."""
    c2w = np.stack([cam.c2w.numpy() for cam in cameras])
    origins, axes = c2w[:, :3, 3], c2w[:, :3, 2]
    projectors = np.eye(3) - axes[:, :, None] * axes[:, None, :]  # onto each axis' normal plane
    a, b = projectors.sum(0), (projectors @ origins[:, :, None]).sum(0)[:, 0]
    # axes spread by less than ~20 degrees leave a nearly singular system
    if np.linalg.eigvalsh(a)[0] < 0.1 * len(cameras):
        return None
    point = np.linalg.solve(a, b)
    in_front = np.einsum("ij,ij->i", point - origins, axes) > 0
    return point if in_front.mean() >= 0.9 else None


def read_mesh(path: Path) -> dict[str, np.ndarray]:
    """`mesh_vertices` (V, 3), `mesh_rgb` (V, 3) in [0, 1] or (0, 3) without colours, and
    `mesh_faces` (F, 3) triangles (quads split in two; (0, 3) for a point cloud) of a mesh file."""
    import meshio

    try:
        mesh = meshio.read(path)
    except Exception as error:  # meshio raises many kinds (ReadError, ValueError, struct.error)
        message = " ".join(str(error).split()) or type(error).__name__
        raise RadfieldError(f"{path}: cannot read mesh ({message})") from None
    cells = mesh.cells_dict
    quads = cells.get("quad", np.zeros((0, 4), np.int64))
    faces = np.concatenate([cells.get("triangle", np.zeros((0, 3), np.int64)), quads[:, :3], quads[:, [0, 2, 3]]])
    channels = [mesh.point_data.get(name) for name in ("red", "green", "blue")]
    if any(c is None for c in channels):
        rgb = np.zeros((0, 3), np.float32)
    else:
        # meshio reads PLY `uchar` properties as int8: reinterpret the bytes
        rgb = np.stack([c.view(np.uint8) if c.dtype == np.int8 else c for c in channels], -1)
        rgb = rgb / 255.0 if np.issubdtype(rgb.dtype, np.integer) else rgb
    return {"mesh_vertices": np.asarray(mesh.points, dtype=np.float32)[:, :3],
            "mesh_rgb": np.clip(rgb, 0.0, 1.0).astype(np.float32),
            "mesh_faces": faces.astype(np.int64)}
