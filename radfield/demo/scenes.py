"""The static demo scenes (`radfield demo-scene blobs|thin|checker|objects|glossy|studio`): each a
few analytic shapes (demo/shapes.py) under a fixed lighting, and the camera rig every demo scene is
photographed by (a golden-angle spiral over the upper hemisphere, test views interleaved in it).
demo/raytrace.py renders them; demo/static.py writes them as a NeRF-synthetic folder."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from radfield.core.geometry.cameras import Camera, look_at
from radfield.demo.shapes import Box, Cylinder, Material, Sphere, Torus
from radfield.errors import RadfieldError


LIGHT = tuple(np.array([0.3, 0.5, 1.0]) / np.linalg.norm([0.3, 0.5, 1.0]))


AMBIENT = 0.35


CAMERA_RADIUS = 4.0


CAMERA_ANGLE_X = 0.69  # about 40 degrees: a scene of radius ~1.2 fills the frame


# Sine of the lowest and highest camera elevation: the lowest stays above every scene's objects
# below the top sphere of 'blobs', the highest keeps look_at's up vector well defined.
_ELEVATION_SIN = (0.15, 0.95)


@dataclass(frozen=True)
class Lighting:
    """One distant light in `direction` plus ambient light (see `shade`). `radius` > 0 (radians)
    makes it a disc light of that angular radius, sampled once per ray (soft shadows and highlights);
    `shadows` traces a shadow ray per sample; `sky` > 0 makes the ambient term a sky dome, brighter
    on upward-facing surfaces."""

    direction: tuple = LIGHT
    ambient: float = AMBIENT
    shadows: bool = False
    radius: float = 0.0
    sky: float = 0.0


@dataclass(frozen=True)
class PointLight:
    """A point light at `position` (world) of `intensity`: irradiance intensity / r² at distance r,
    hard shadows toward the point (when the scene's Lighting has shadows). It replaces the scene's
    distant light in `shade`; the scene's ambient (and sky) term stays. `radfield demo-scene olat`
    moves one through the studio scene (demo/olat.py)."""

    position: tuple
    intensity: float = 1.0


@dataclass(frozen=True)
class Scene:
    name: str
    description: str
    primitives: tuple
    mesh: bool = True  # write mesh.ply; without it a run builds its envelope from the alpha masks
    train_views: int = 40  # what `radfield demo-scene NAME` writes unless told otherwise
    test_views: int = 8
    samples: int = 2  # per pixel: samples x samples rays
    jitter: bool = False  # stratified jittered rays (a path tracer's sampler) instead of a regular grid
    lighting: Lighting = Lighting()


def _solid(r, g, b) -> Material:
    return Material((r, g, b))


def _wire_cube(half: float, radius: float) -> tuple:
    """Rods on the 12 edges of a cube (coloured by axis) and a small sphere on each corner."""
    corners = [(2 * np.array(c, dtype=float) - 1) * half for c in np.ndindex(2, 2, 2)]
    axis_colours = [_solid(0.9, 0.2, 0.2), _solid(0.2, 0.8, 0.25), _solid(0.25, 0.35, 0.95)]
    rods = [
        Cylinder(tuple(a), tuple(b), radius, axis_colours[int(np.argmax(np.abs(b - a)))])
        for k, a in enumerate(corners)
        for b in corners[k + 1 :]
        if np.count_nonzero(a != b) == 1
    ]
    joints = [Sphere(tuple(c), 1.8 * radius, _solid(0.9, 0.9, 0.85)) for c in corners]
    return tuple(rods + joints)


SCENES: dict[str, Scene] = {
    scene.name: scene
    for scene in (
        Scene(
            "blobs",
            "a few coloured spheres on a box: the default demo, easy",
            (
                Box((0.0, 0.0, -0.3), (0.55, 0.55, 0.2), _solid(0.9, 0.55, 0.15), yaw=20.0),
                Sphere((0.0, 0.0, 0.45), 0.35, _solid(0.85, 0.15, 0.15)),
                Sphere((0.6, -0.45, 0.1), 0.25, _solid(0.2, 0.75, 0.3)),
                Sphere((-0.55, 0.4, 0.05), 0.3, _solid(0.2, 0.35, 0.9)),
                Sphere((0.45, 0.55, -0.35), 0.15, _solid(0.75, 0.3, 0.8)),
            ),
        ),
        Scene(
            "thin",
            "a wire-frame cube of sub-pixel rods with a diagonal brace: thin structures",
            _wire_cube(0.7, 0.025) + (Cylinder((-0.7, -0.7, -0.7), (0.7, 0.7, 0.7), 0.02, _solid(0.95, 0.8, 0.2)),),
        ),
        Scene(
            "checker",
            "a checkered sphere and slab, a striped cylinder and box: high-frequency textures",
            (
                Box((0.0, 0.0, -0.35), (0.9, 0.9, 0.05), Material((0.95, 0.95, 0.95), "checker", (0.1, 0.1, 0.1), 6.0)),
                Sphere((0.0, 0.0, 0.15), 0.45, Material((0.95, 0.9, 0.8), "checker", (0.6, 0.05, 0.1), 8.0)),
                Cylinder(
                    (0.6, 0.5, -0.3),
                    (0.6, 0.5, 0.55),
                    0.15,
                    Material((0.95, 0.85, 0.1), "stripes", (0.1, 0.2, 0.7), 10.0),
                ),
                Box(
                    (-0.55, -0.5, -0.12),
                    (0.18, 0.18, 0.18),
                    Material((0.2, 0.7, 0.3), "stripes", (0.95, 0.95, 0.95), 12.0, (1.0, 0.0, 0.0)),
                    yaw=35.0,
                ),
            ),
        ),
        Scene(
            "objects",
            "separate objects (sphere, cube, torus, cylinder, two thin rods) and no mesh.ply: the visual hull",
            (
                Sphere((-0.55, -0.45, -0.05), 0.28, _solid(0.85, 0.2, 0.15)),
                Box((0.55, -0.5, -0.15), (0.2, 0.2, 0.2), _solid(0.95, 0.6, 0.15), yaw=25.0),
                Torus((0.0, 0.5, 0.0), (0.3, 0.0, 1.0), 0.38, 0.1, _solid(0.2, 0.75, 0.3)),
                Cylinder((-0.65, 0.45, -0.35), (-0.65, 0.45, 0.25), 0.12, _solid(0.2, 0.35, 0.9)),
                Cylinder((0.6, 0.35, -0.4), (0.6, 0.35, 0.5), 0.025, _solid(0.9, 0.9, 0.85)),
                Cylinder((0.05, -0.2, -0.45), (0.1, -0.15, 0.45), 0.02, _solid(0.75, 0.3, 0.8)),
            ),
            mesh=False,
        ),
        Scene(
            "glossy",
            "glossy and matte objects on a matte slab (moving specular highlights), 100 + 20 views: the study scene",
            (
                Box((0.0, 0.0, -0.45), (0.85, 0.85, 0.06), _solid(0.8, 0.78, 0.72)),
                Sphere((-0.35, -0.3, -0.07), 0.32, Material((0.8, 0.12, 0.1), specular=0.6, shininess=40.0)),
                Sphere((0.45, 0.35, -0.17), 0.22, Material((0.15, 0.3, 0.85), specular=0.5, shininess=80.0)),
                Box((0.4, -0.4, -0.21), (0.18, 0.18, 0.18), _solid(0.2, 0.7, 0.3), yaw=30.0),
                Torus((-0.35, 0.45, -0.28), (0.0, 0.0, 1.0), 0.25, 0.09,
                      Material((0.9, 0.65, 0.15), specular=0.5, shininess=24.0)),
                Cylinder((0.05, 0.05, -0.39), (0.05, 0.05, 0.35), 0.07, Material((0.85, 0.85, 0.85), specular=0.4)),
            ),
            train_views=100,
            test_views=20,
        ),
        Scene(
            "studio",
            "the glossy scene's objects on a round plinth, rendered like a path tracer (8x8 jittered rays per pixel, soft shadows "
            "of a disc light, sky light, moderate highlights), 100 + 20 views: the issue-11 kind of scene",
            (
                # A round plinth instead of glossy's thin square slab: a smooth silhouette without
                # corners, sides (0.3 high) of >= 2 pixels at 64x64 from every camera.
                Cylinder((0.0, 0.0, -0.69), (0.0, 0.0, -0.39), 0.85, _solid(0.8, 0.78, 0.72)),
                Sphere((-0.35, -0.3, -0.07), 0.32, Material((0.8, 0.12, 0.1), specular=0.5, shininess=20.0)),
                Sphere((0.45, 0.35, -0.17), 0.22, Material((0.15, 0.3, 0.85), specular=0.4, shininess=30.0)),
                Box((0.4, -0.4, -0.21), (0.18, 0.18, 0.18), _solid(0.2, 0.7, 0.3), yaw=30.0),
                Torus((-0.35, 0.45, -0.28), (0.0, 0.0, 1.0), 0.25, 0.09,
                      Material((0.9, 0.65, 0.15), specular=0.4, shininess=16.0)),
                Cylinder((0.05, 0.05, -0.39), (0.05, 0.05, 0.35), 0.07, Material((0.85, 0.85, 0.85), specular=0.3,
                                                                                 shininess=12.0)),
            ),
            train_views=100,
            test_views=20,
            samples=8,
            jitter=True,
            # ambient 0.5: a white world light of half the sun's strength, as a path tracer lit by
            # the white surroundings the images are shown on (the other scenes: 0.35)
            lighting=Lighting(ambient=0.5, shadows=True, radius=0.1, sky=0.5),
        ),
    )
}


def get_scene(name: str) -> Scene:
    if name not in SCENES:
        raise RadfieldError(f"unknown synthetic scene {name!r} (available: {', '.join(SCENES)})")
    return SCENES[name]


def check_counts(name: str, n_train: int, n_test: int, each: int, each_words: str, size: int) -> None:
    """One error line for a dynamic or relighting scene asked with fewer than 1 train and 1 test
    camera, fewer than 1 of what each camera repeats over (`each`: times, lights; `each_words`: "1
    time") or images under 8 pixels."""
    if n_train < 1 or n_test < 1 or each < 1 or size < 8:
        raise RadfieldError(f"demo-scene {name}: need at least 1 train and 1 test camera, {each_words} and "
                            f"size >= 8 (got {n_train}, {n_test}, {each}, {size})")


def orbit_cameras(n_train: int, n_test: int, size: int, seed: int = 0) -> tuple[list[Camera], list[Camera]]:
    """Train and test cameras (size x size pixels) on one golden-angle spiral over the upper
    hemisphere (radius CAMERA_RADIUS, looking at the origin, +z up); the seed turns the spiral."""
    n = n_train + n_test
    k = np.arange(n)
    z = _ELEVATION_SIN[0] + (_ELEVATION_SIN[1] - _ELEVATION_SIN[0]) * (k + 0.5) / n
    azimuth = np.random.default_rng(seed).uniform(0, 2 * math.pi) + k * math.pi * (3 - math.sqrt(5))
    ring = np.sqrt(1 - z**2)
    eyes = CAMERA_RADIUS * np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], -1)
    # Test views spread evenly through the spiral (so over all heights), never on a train view.
    is_test = np.zeros(n, dtype=bool)
    is_test[np.round(np.linspace(0, n - 1, n_test)).astype(int)] = True
    focal = 0.5 * size / math.tan(0.5 * CAMERA_ANGLE_X)

    def camera(index: int, name: str) -> Camera:
        return Camera(focal, focal, size / 2, size / 2, size, size, look_at(eyes[index], (0, 0, 0), (0, 0, 1)), name)

    train = [camera(idx, f"r_{m}") for m, idx in enumerate(np.flatnonzero(~is_test))]
    test = [camera(idx, f"r_{m}") for m, idx in enumerate(np.flatnonzero(is_test))]
    return train, test
