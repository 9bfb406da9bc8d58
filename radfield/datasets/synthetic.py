"""Tiny synthetic scenes with exact ground truth, ray traced analytically (no network, no data files).

`generate_scene(name, out_dir)` writes a NeRF-synthetic folder:

    transforms_train.json, transforms_test.json   camera_angle_x + OpenGL camera-to-world per frame
    train/r_i.png, test/r_i.png                   RGBA, transparent background, supersampled (2x2 rays
                                                  per pixel; 'studio': 8x8 jittered)
    train/r_i_depth.exr, test/r_i_depth.exr       z-depth of the pixel-centre ray (0 on background)
    mesh.ply                                      the scene triangulated, with vertex colours
                                                  (not for scenes with `mesh=False`, such as 'objects')
    scene.json                                    the exact analytic shapes, light and cameras

Shading is Lambertian under one fixed directional light plus ambient, so colour is view-independent
and a radiance field can fit it exactly, except on glossy materials (`Material.specular` > 0, the
'glossy' and 'studio' scenes): a white Blinn-Phong highlight k_s · max(0, n·h)^p, h = normalise(l − d),
that moves over the surface with the viewing direction d (what SH colour must fit).

'studio' is rendered the way a path tracer renders an object scene: 8x8 stratified jittered rays per
pixel (edge pixels hold nearly their exact area coverage, consistently across views, where the 2x2
grid of the other scenes quantises it into five levels that differ from view to view), a disc light
of angular radius 0.1 rad sampled once per ray with a shadow ray (soft shadows), a sky-dome ambient
term of strength 0.5 (a white world light), a round plinth instead of glossy's thin slab, and highlights of shininess 12-30 (view-space lobe width 2/sqrt(p) = 21-33 degrees, within
reach of SH degree 3, against glossy's 80: 13 degrees). The jitter of every view is drawn from
(seed, split, view index), so the scene is reproducible.
Cameras sit on a sphere around the origin, looking at it:
a golden-angle (Fibonacci) spiral over the upper hemisphere, with the test views interleaved in it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radfield.core.geometry.cameras import Camera, look_at, opencv_to_opengl
from radfield.errors import RadfieldError
from radfield.util.atomic import new_folder
from radfield.datasets.images import write_image
from radfield.datasets.shapes import Box, Cylinder, Material, Sphere, Torus

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
    moves one through the studio scene (datasets/olat.py)."""

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


def intersect(scene: Scene, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hit of rays from o ((3,) or (R, 3)) along unit d (R, 3): distance (R,) (inf on a miss),
    unit normal (R, 3) and the index of the primitive hit (R,) (-1 on a miss)."""
    o = np.broadcast_to(np.asarray(o, dtype=np.float64), d.shape)
    t = np.full(len(d), np.inf)
    normal = np.zeros_like(d)
    index = np.full(len(d), -1)
    for k, primitive in enumerate(scene.primitives):
        # Only rays through the bounding sphere: thin rods cover a few pixels of a view.
        centre, radius = primitive.bounding_sphere
        oc = o - centre
        b = np.einsum("ij,ij->i", d, oc)
        rows = np.flatnonzero(b * b - np.einsum("ij,ij->i", oc, oc) + radius**2 >= 0)
        t_k, n_k = primitive.intersect(o[rows], d[rows])
        closer = t_k < t[rows]
        rows, t_k, n_k = rows[closer], t_k[closer], n_k[closer]
        t[rows], normal[rows], index[rows] = t_k, n_k, k
    return t, normal, index


def shade(scene: Scene, o: np.ndarray, d: np.ndarray, t: np.ndarray, normal: np.ndarray, index: np.ndarray,
          light: np.ndarray | None = None, points: np.ndarray | None = None,
          point_light: PointLight | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Colour (R, 3) of the hits of `intersect` and its specular part (R,), under the scene's light
    (or per-ray light directions `light` (R, 3), the samples of an area light; or `point_light`):
    albedo · (ambient(n) + (1 − A) max(0, n·l) V E) + k_s max(0, n·h)^p [n·l > 0] V E, h = normalise(l − d),
    with ambient(n) = A (constant), or A (1 + s n_z)/(1 + s) under a sky dome of `sky` = s,
    V the light's visibility from the hit point (1 without `Lighting.shadows`) and E its irradiance
    relative to the distant light's: 1, or intensity / r² for a point light at distance r (l then
    points from each hit to it). `points` (R, 3): where the albedo is looked up (default the hits
    o + t·d; a deformed scene's rest-space points, so the texture moves with the material)."""
    lighting = scene.lighting
    o = np.broadcast_to(np.asarray(o, dtype=np.float64), d.shape)
    distance = None  # to a point light, per ray
    if point_light is not None:
        light, distance = _towards(point_light, o, d, t, index)
    if light is None:
        light = np.asarray(lighting.direction)
        n_l = normal @ light
    else:
        n_l = np.einsum("ij,ij->i", normal, light)
    light = np.broadcast_to(light, d.shape)
    visible = np.ones(len(d))  # V E: the light arriving at each hit
    if lighting.shadows:
        hit = np.flatnonzero((index >= 0) & (n_l > 0))
        # Offset along the normal so the shadow ray does not hit its own surface.
        shadow_from = o[hit] + t[hit, None] * d[hit] + 1e-6 * normal[hit]
        blocker = intersect(scene, shadow_from, light[hit])[0]
        # a point light is shadowed only by what lies between the hit and the light
        visible[hit] = np.isinf(blocker) if distance is None else blocker >= distance[hit]
    if distance is not None:
        visible = visible * (point_light.intensity / distance**2)  # 1/r² falloff
    ambient = lighting.ambient
    if lighting.sky:
        ambient = lighting.ambient * (1 + lighting.sky * normal[:, 2]) / (1 + lighting.sky)
    diffuse = ambient + (1 - lighting.ambient) * np.clip(n_l, 0.0, None) * visible
    half = light - d
    half = half / np.linalg.norm(half, axis=-1, keepdims=True)
    colour = np.zeros_like(d)
    specular = np.zeros(len(d))
    for k, primitive in enumerate(scene.primitives):
        rows = index == k
        material = primitive.material
        colour[rows] = material.albedo(o[rows] + t[rows, None] * d[rows] if points is None else points[rows])
        colour[rows] *= diffuse[rows, None]
        if material.specular > 0:  # Blinn-Phong, lit side only
            n_h = np.clip(np.einsum("ij,ij->i", normal[rows], half[rows]), 0.0, None)
            specular[rows] = material.specular * n_h**material.shininess * (n_l[rows] > 0) * visible[rows]
            colour[rows] += specular[rows, None]
    return np.clip(colour, 0.0, 1.0), specular


def _towards(point_light: PointLight, o: np.ndarray, d: np.ndarray, t: np.ndarray,
             index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (R, 3) from each hit o + t·d to the point light and the distances (R,) to
    it; rays that miss get +z and distance 1 (they are not shaded)."""
    light = np.zeros_like(d)
    light[:, 2] = 1.0
    distance = np.ones(len(d))
    hit = np.flatnonzero(index >= 0)
    towards = np.asarray(point_light.position, dtype=np.float64) - (o[hit] + t[hit, None] * d[hit])
    distance[hit] = np.linalg.norm(towards, axis=-1)
    light[hit] = towards / distance[hit, None]
    return light, distance


def trace(scene: Scene, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shaded colour (R, 3) and hit distance (R,) (inf on a miss) of rays from o (3,) along unit d (R, 3)."""
    t, normal, index = intersect(scene, o, d)
    return shade(scene, o, d, t, normal, index)[0], t


def strata(side: int) -> np.ndarray:
    """The cells (side², 2) of a side × side grid over the unit square, as integer (row, column)
    corners, row-major: what stratified sampling draws one point in each of."""
    return np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1).reshape(-1, 2)


def pixel_offsets(samples: int, jitter: bool, pixels: int, rng: np.random.Generator | None) -> np.ndarray:
    """Sample positions inside each pixel (pixels, samples², 2) in [0, 1)²: the centres of a
    samples × samples grid, or with `jitter` one uniform point in each of its cells (stratified
    sampling, as a path tracer's pixel sampler)."""
    grid = strata(samples)
    if not jitter:
        return np.broadcast_to((grid + 0.5) / samples, (pixels, samples * samples, 2))
    return (grid + rng.random((pixels, samples * samples, 2))) / samples


def light_samples(lighting: Lighting, count: int, pixels: int, rng: np.random.Generator) -> np.ndarray:
    """Directions (pixels, count, 3) towards a disc light of angular radius `lighting.radius`
    around `lighting.direction`: per pixel one jittered point in each cell of a stratified grid
    over the disc (concentric map), in a random order, so the pixel's samples pair with the light's
    strata at random (soft shadows with little noise)."""
    side = math.isqrt(count)
    uv = (strata(side) + rng.random((pixels, count, 2))) / side
    order = np.argsort(rng.random((pixels, count)), axis=1)
    uv = np.take_along_axis(uv, order[..., None], axis=1)
    # Shirley-Chiu concentric map of the unit square onto the unit disc (equal area)
    a, b = 2 * uv[..., 0] - 1, 2 * uv[..., 1] - 1
    major = np.abs(a) > np.abs(b)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(major, a, b)
        phi = np.where(major, math.pi / 4 * b / a, math.pi / 2 - math.pi / 4 * a / b)
    phi = np.nan_to_num(phi)
    l = np.asarray(lighting.direction)
    e1 = np.cross(l, [1.0, 0.0, 0.0] if abs(l[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(l, e1)
    spread = math.tan(lighting.radius) * r
    out = l + spread[..., None] * (np.cos(phi)[..., None] * e1 + np.sin(phi)[..., None] * e2)
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def render_view(scene: Scene, camera: Camera, samples: int | None = None,
                rng: np.random.Generator | None = None, deform: "Deformation | None" = None,
                point_light: PointLight | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Premultiplied RGBA (H, W, 4) float32 averaged over samples x samples rays per pixel (default
    the scene's own `samples`; jittered in their cells if `scene.jitter`, drawn from `rng`), and
    the z-depth (H, W) float32 of the pixel-centre ray (0 where it misses). With `deform` the
    scene's shapes are seen deformed by that map (`Deformation.intersect`), through the same rays;
    with `point_light` the scene is lit by it instead of its distant light (see `shade`)."""
    samples = scene.samples if samples is None else samples
    height, width = camera.height, camera.width
    if rng is None:
        rng = np.random.default_rng(0)
    offsets = pixel_offsets(samples, scene.jitter, height * width, rng).reshape(height, width, -1, 2)
    centre = np.full((height, width, 1, 2), 0.5)
    offsets = np.concatenate([offsets, centre], axis=2)  # last: the pixel centre, for depth
    i = np.arange(height)[:, None, None] + offsets[..., 0]
    j = np.arange(width)[None, :, None] + offsets[..., 1]
    d_cam = np.stack([(j - camera.cx) / camera.fx, (i - camera.cy) / camera.fy, np.ones_like(i)], -1)
    d_cam /= np.linalg.norm(d_cam, axis=-1, keepdims=True)
    c2w = camera.c2w.numpy()
    d = d_cam.reshape(-1, 3) @ c2w[:3, :3].T
    o = c2w[:3, 3]
    if deform is None:
        t, normal, index = intersect(scene, o, d)
        points = None
    else:
        t, normal, index, points = deform.intersect(scene, o, d)
    light = None
    if scene.lighting.radius > 0 and point_light is None:  # an area light: one light sample per ray; the centre ray (depth only) its centre
        light = light_samples(scene.lighting, samples * samples, height * width, rng)
        centre_light = np.broadcast_to(np.asarray(scene.lighting.direction), (height * width, 1, 3))
        light = np.concatenate([light, centre_light], 1).reshape(-1, 3)
    colour, _ = shade(scene, o, d, t, normal, index, light, points, point_light)
    colour, t = colour.reshape(d_cam.shape), t.reshape(d_cam.shape[:-1])
    hit = np.isfinite(t)
    rgba = np.concatenate([colour[:, :, :-1], hit[:, :, :-1, None]], -1).mean(axis=2)
    depth = np.where(hit[:, :, -1], t[:, :, -1] * d_cam[:, :, -1, 2], 0.0)
    return rgba.astype(np.float32), depth.astype(np.float32)


# --- deformed scenes: the ground truth of an edit (docs/usage.md "radfield demo-scene") --------

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


def write_mesh(scene: Scene, path: Path, deform: Deformation | None = None) -> None:
    """The scene's shapes triangulated into one PLY, each vertex coloured by its albedo (with
    `deform`, the vertices moved by its map, coloured by their rest-space albedo)."""
    import pyvista as pv  # VTK is slow to import; only mesh writing needs it

    parts = []
    for primitive in scene.primitives:
        part = primitive.mesh().triangulate()
        part.point_data["colors"] = np.rint(
            primitive.material.albedo(np.asarray(part.points, dtype=np.float64)) * 255
        ).astype(np.uint8)
        if deform is not None:
            part.points = deform.forward(np.asarray(part.points, dtype=np.float64))
        parts.append(part)
    pv.merge(parts).save(path, texture="colors")


def generate_scene(
    name: str, out_dir: str | os.PathLike, n_train: int | None = None, n_test: int | None = None, size: int = 64,
    seed: int = 0, mesh: bool = True, deform: str | None = None, workers: int = 1,
) -> Path:
    """Render scene `name` into a new NeRF-synthetic folder `out_dir` (see the module docstring);
    n_train / n_test default to the scene's own counts (Scene.train_views / test_views).
    mesh=False leaves out `mesh.ply` (its writer needs pyvista, which a GPU machine may lack).
    Written to a temporary sibling folder and renamed, so `out_dir` is either complete or absent;
    an existing non-empty `out_dir` is refused. `deform` ('twist', 'bend' or 'squash', `DEFORMATIONS`)
    renders the scene's shapes deformed by that map through the same cameras (the ground truth of the
    same map applied by `radfield edit`) and writes the map as an edit spec, `deform.yaml`.
    workers > 1 renders that many views at once in worker processes (the same images: every view's
    samples come from its own (seed, split, view) stream)."""
    scene = get_scene(name)
    deformation = None if deform is None else get_deformation(deform)
    if deformation is not None and (scene.lighting.shadows or scene.lighting.radius > 0):
        raise RadfieldError(f"demo-scene {name}: --deform needs a scene without shadows or an area light "
                            f"(its shadow rays would have to march the deformed scene too)")
    out_dir = Path(out_dir)
    n_train = scene.train_views if n_train is None else n_train
    n_test = scene.test_views if n_test is None else n_test
    if n_train < 1 or n_test < 1 or size < 8:
        raise RadfieldError(
            f"generate_scene: need n_train >= 1, n_test >= 1 and size >= 8 (got {n_train}, {n_test}, {size})"
        )
    if workers < 1:
        raise RadfieldError(f"generate_scene: need workers >= 1 (got {workers})")
    with new_folder(out_dir) as tmp:   # complete or absent (util/atomic.py)
        train, test = orbit_cameras(n_train, n_test, size, seed)
        for split, cameras in (("train", train), ("test", test)):
            _write_split(name, tmp, split, cameras, seed, deform, workers)
        if scene.mesh and mesh:
            write_mesh(scene, tmp / "mesh.ply", deformation)
        description = _describe(scene, seed)
        if deformation is not None:
            import yaml

            description["deform"] = {"name": deform, **dataclasses.asdict(deformation), "edit_spec": deformation.spec()}
            (tmp / "deform.yaml").write_text(
                f"# radfield edit RUN --spec deform.yaml -o EDITED: the map this scene ({name}, {deform}) was rendered with\n"
                + yaml.safe_dump({"operations": [deformation.spec()]}, sort_keys=False, default_flow_style=None))
        (tmp / "scene.json").write_text(json.dumps(description, indent=2))
    return out_dir


def _write_split(name: str, root: Path, split: str, cameras: list[Camera], seed: int, deform: str | None,
                 workers: int) -> None:
    (root / split).mkdir()
    views = [(name, root, split, k, camera, seed, deform) for k, camera in enumerate(cameras)]
    if workers > 1 and len(views) > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        # spawned, not forked: the parent may hold torch's thread pools
        with ProcessPoolExecutor(min(workers, len(views)), mp_context=multiprocessing.get_context("spawn")) as pool:
            frames = list(pool.map(_write_view, views))
    else:
        frames = [_write_view(view) for view in views]
    meta = {"camera_angle_x": CAMERA_ANGLE_X, "frames": frames}
    (root / f"transforms_{split}.json").write_text(json.dumps(meta, indent=2))


def _write_view(view: tuple) -> dict:
    """Render view k of a split and write its image and depth; its frame entry. Each view's own
    sample pattern, reproducible from (seed, split, view)."""
    name, root, split, k, camera, seed, deform = view
    rng = np.random.default_rng([seed, ("train", "test").index(split), k])
    rgba, depth = render_view(get_scene(name), camera, rng=rng, deform=None if deform is None else get_deformation(deform))
    write_image(root / split / f"{camera.name}.png", rgba)
    write_image(root / split / f"{camera.name}_depth.exr", depth)
    return {"file_path": f"./{split}/{camera.name}", "depth_file_path": f"./{split}/{camera.name}_depth.exr",
            "transform_matrix": opencv_to_opengl(camera.c2w).tolist()}


def _describe(scene: Scene, seed: int) -> dict:
    """scene.json: the exact shapes (type + parameters), light and camera rig."""
    return {
        "name": scene.name,
        "description": scene.description,
        "seed": seed,
        "light_direction": list(scene.lighting.direction),
        "ambient": scene.lighting.ambient,
        "lighting": dataclasses.asdict(scene.lighting),
        "samples_per_pixel": scene.samples**2,
        "jittered": scene.jitter,
        "camera_radius": CAMERA_RADIUS,
        "camera_angle_x": CAMERA_ANGLE_X,
        "depth": "z-depth along the camera axis of the pixel-centre ray, 0 on background",
        "primitives": [{"type": type(p).__name__.lower(), **dataclasses.asdict(p)} for p in scene.primitives],
    }
