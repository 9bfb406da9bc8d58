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
import math
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radfield.core.geometry.cameras import Camera, look_at, opencv_to_opengl
from radfield.errors import RadfieldError
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
          light: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Colour (R, 3) of the hits of `intersect` and its specular part (R,), under the scene's light
    (or per-ray light directions `light` (R, 3), the samples of an area light):
    albedo · (ambient(n) + (1 − A) max(0, n·l) V) + k_s max(0, n·h)^p [n·l > 0] V, h = normalise(l − d),
    with ambient(n) = A (constant), or A (1 + s n_z)/(1 + s) under a sky dome of `sky` = s, and
    V the light's visibility from the hit point (1 without `Lighting.shadows`)."""
    lighting = scene.lighting
    o = np.broadcast_to(np.asarray(o, dtype=np.float64), d.shape)
    if light is None:
        light = np.asarray(lighting.direction)
        n_l = normal @ light
    else:
        n_l = np.einsum("ij,ij->i", normal, light)
    light = np.broadcast_to(light, d.shape)
    visible = np.ones(len(d))
    if lighting.shadows:
        hit = np.flatnonzero((index >= 0) & (n_l > 0))
        # Offset along the normal so the shadow ray does not hit its own surface.
        points = o[hit] + t[hit, None] * d[hit] + 1e-6 * normal[hit]
        visible[hit] = np.isinf(intersect(scene, points, light[hit])[0])
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
        colour[rows] = material.albedo(o[rows] + t[rows, None] * d[rows])
        colour[rows] *= diffuse[rows, None]
        if material.specular > 0:  # Blinn-Phong, lit side only
            n_h = np.clip(np.einsum("ij,ij->i", normal[rows], half[rows]), 0.0, None)
            specular[rows] = material.specular * n_h**material.shininess * (n_l[rows] > 0) * visible[rows]
            colour[rows] += specular[rows, None]
    return np.clip(colour, 0.0, 1.0), specular


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
                rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Premultiplied RGBA (H, W, 4) float32 averaged over samples x samples rays per pixel (default
    the scene's own `samples`; jittered in their cells if `scene.jitter`, drawn from `rng`), and
    the z-depth (H, W) float32 of the pixel-centre ray (0 where it misses)."""
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
    t, normal, index = intersect(scene, o, d)
    light = None
    if scene.lighting.radius > 0:  # an area light: one light sample per ray; the centre ray (depth only) its centre
        light = light_samples(scene.lighting, samples * samples, height * width, rng)
        centre_light = np.broadcast_to(np.asarray(scene.lighting.direction), (height * width, 1, 3))
        light = np.concatenate([light, centre_light], 1).reshape(-1, 3)
    colour, _ = shade(scene, o, d, t, normal, index, light)
    colour, t = colour.reshape(d_cam.shape), t.reshape(d_cam.shape[:-1])
    hit = np.isfinite(t)
    rgba = np.concatenate([colour[:, :, :-1], hit[:, :, :-1, None]], -1).mean(axis=2)
    depth = np.where(hit[:, :, -1], t[:, :, -1] * d_cam[:, :, -1, 2], 0.0)
    return rgba.astype(np.float32), depth.astype(np.float32)


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


def write_mesh(scene: Scene, path: Path) -> None:
    """The scene's shapes triangulated into one PLY, each vertex coloured by its albedo."""
    import pyvista as pv  # VTK is slow to import; only mesh writing needs it

    parts = []
    for primitive in scene.primitives:
        part = primitive.mesh().triangulate()
        part.point_data["colors"] = np.rint(
            primitive.material.albedo(np.asarray(part.points, dtype=np.float64)) * 255
        ).astype(np.uint8)
        parts.append(part)
    pv.merge(parts).save(path, texture="colors")


def generate_scene(
    name: str, out_dir: str | os.PathLike, n_train: int | None = None, n_test: int | None = None, size: int = 64,
    seed: int = 0, mesh: bool = True,
) -> Path:
    """Render scene `name` into a new NeRF-synthetic folder `out_dir` (see the module docstring);
    n_train / n_test default to the scene's own counts (Scene.train_views / test_views).
    mesh=False leaves out `mesh.ply` (its writer needs pyvista, which a GPU machine may lack).
    Written to a temporary sibling folder and renamed, so `out_dir` is either complete or absent;
    an existing non-empty `out_dir` is refused."""
    scene = get_scene(name)
    out_dir = Path(out_dir)
    n_train = scene.train_views if n_train is None else n_train
    n_test = scene.test_views if n_test is None else n_test
    if n_train < 1 or n_test < 1 or size < 8:
        raise RadfieldError(
            f"generate_scene: need n_train >= 1, n_test >= 1 and size >= 8 (got {n_train}, {n_test}, {size})"
        )
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise RadfieldError(f"{out_dir}: already exists and is not an empty folder; refusing to overwrite it")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    try:
        train, test = orbit_cameras(n_train, n_test, size, seed)
        for split, cameras in (("train", train), ("test", test)):
            _write_split(scene, tmp, split, cameras, seed)
        if scene.mesh and mesh:
            write_mesh(scene, tmp / "mesh.ply")
        (tmp / "scene.json").write_text(json.dumps(_describe(scene, seed), indent=2))
        tmp.chmod(0o755)  # mkdtemp makes it private
        if out_dir.exists():
            out_dir.rmdir()
        os.replace(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def _write_split(scene: Scene, root: Path, split: str, cameras: list[Camera], seed: int) -> None:
    (root / split).mkdir()
    frames = []
    for k, camera in enumerate(cameras):
        # Each view's own sample pattern, reproducible from (seed, split, view).
        rng = np.random.default_rng([seed, ("train", "test").index(split), k])
        rgba, depth = render_view(scene, camera, rng=rng)
        write_image(root / split / f"{camera.name}.png", rgba)
        write_image(root / split / f"{camera.name}_depth.exr", depth)
        frames.append(
            {
                "file_path": f"./{split}/{camera.name}",
                "depth_file_path": f"./{split}/{camera.name}_depth.exr",
                "transform_matrix": opencv_to_opengl(camera.c2w).tolist(),
            }
        )
    meta = {"camera_angle_x": CAMERA_ANGLE_X, "frames": frames}
    (root / f"transforms_{split}.json").write_text(json.dumps(meta, indent=2))


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
