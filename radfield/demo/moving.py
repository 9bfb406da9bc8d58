"""`radfield demo-scene moving`: the `objects` scene's opaque shapes moving and turning over time,
ray traced exactly at each time (raytrace.render_view, 2x2 rays per pixel), as a D-NeRF dataset
(demo/timelapse.py). It covers what the smoke volume does not: time-varying opaque surfaces,
sharp silhouettes and shading that changes as faces turn to the light.

Each shape k moves rigidly over ξ ∈ [0, 1]: turned by angle_k · ξ about axis_k through its own
centre (its bounding sphere's), then shifted by offset_k ξ + swirl_k sin(π ξ). Boxes turn about
z only (their yaw). One thin rod stays still. Materials are solid colours, so nothing slides
over a surface.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from radfield.core.geometry.cameras import Camera
from radfield.demo.shapes import Box, Cylinder, Sphere, Torus
from radfield.demo.scenes import Scene, get_scene
from radfield.demo.raytrace import render_view


@dataclass(frozen=True)
class Motion:
    offset: tuple = (0.0, 0.0, 0.0)
    swirl: tuple = (0.0, 0.0, 0.0)
    axis: tuple = (0.0, 0.0, 1.0)
    angle: float = 0.0   # radians turned over ξ ∈ [0, 1]

    def shift(self, xi: float) -> np.ndarray:
        return np.multiply(self.offset, xi) + np.multiply(self.swirl, math.sin(math.pi * xi))

    def rotation(self, xi: float) -> np.ndarray:
        """Rodrigues' rotation by angle · ξ about the axis."""
        u = np.asarray(self.axis, float) / np.linalg.norm(self.axis)
        cross = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
        turn = self.angle * xi
        return np.eye(3) + math.sin(turn) * cross + (1 - math.cos(turn)) * cross @ cross


# one per shape of the `objects` scene, in its order: sphere, box, torus, cylinder, two thin rods
MOTIONS = (
    Motion(offset=(0.35, 0.1, 0.0), swirl=(0.0, 0.0, 0.3)),                          # the sphere bounces across
    Motion(offset=(0.0, 0.3, 0.1), angle=math.pi / 2),                               # the box slides and turns
    Motion(offset=(0.0, 0.0, 0.1), swirl=(0.15, 0.0, 0.0), angle=2 * math.pi / 3),  # the torus precesses
    Motion(offset=(0.2, 0.0, 0.0), axis=(1.0, 0.0, 0.0), angle=0.5),                 # the cylinder tilts
    Motion(),                                                                         # a thin rod stays
    Motion(axis=(1.0, 0.0, 0.0), angle=0.6),                                          # a thin rod tips over
)


def moved(shape, motion: Motion, xi: float):
    """The shape after its motion at time ξ (a new shape of the same type)."""
    pivot = np.asarray(shape.bounding_sphere[0], float)
    rotation, target = motion.rotation(xi), pivot + motion.shift(xi)

    def carry(point) -> tuple:
        return tuple(target + rotation @ (np.asarray(point, float) - pivot))

    if isinstance(shape, Sphere):
        return dataclasses.replace(shape, center=tuple(target))
    if isinstance(shape, Box):  # turns about z only (its yaw): MOTIONS keeps the box's axis z
        return dataclasses.replace(shape, center=tuple(target), yaw=shape.yaw + math.degrees(motion.angle * xi))
    if isinstance(shape, Cylinder):
        return dataclasses.replace(shape, start=carry(shape.start), end=carry(shape.end))
    if isinstance(shape, Torus):
        return dataclasses.replace(shape, center=tuple(target), axis=tuple(rotation @ np.asarray(shape.axis, float)))
    raise TypeError(f"no motion for {type(shape).__name__}")


def scene_at(xi: float) -> Scene:
    """The `objects` scene with every shape moved to time ξ."""
    base = get_scene("objects")
    return dataclasses.replace(base, name="moving",
                               primitives=tuple(moved(p, m, xi) for p, m in zip(base.primitives, MOTIONS)))


def render(camera: Camera, xi: float) -> np.ndarray:
    """Premultiplied RGBA (H, W, 4) float32 of the scene at time ξ (2x2 rays per pixel)."""
    return render_view(scene_at(xi), camera)[0]


def describe() -> dict:
    """What scene.json says: the shapes at ξ = 0 and their motions."""
    base = get_scene("objects")
    return {
        "description": "the objects scene's shapes moving and turning over time (opaque surfaces)",
        "motion": "each shape turned by angle * t about axis through its centre, then shifted by "
                  "offset * t + swirl * sin(pi t); boxes turn about z (yaw)",
        "samples_per_pixel": base.samples**2,
        "light_direction": list(base.lighting.direction),
        "ambient": base.lighting.ambient,
        "primitives": [{"type": type(p).__name__.lower(), **dataclasses.asdict(p), "motion": dataclasses.asdict(m)}
                       for p, m in zip(base.primitives, MOTIONS)],
    }
