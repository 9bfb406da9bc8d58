"""The demo scenes' renderer: exact ray-shape intersections of the analytic shapes, Lambert shading
under the scene's light plus ambient (Blinn-Phong highlights on glossy materials, shadows and a
disc light where the scene's Lighting says), and supersampled pixels (demo/static.py's module
docstring describes what each scene asks for)."""

from __future__ import annotations

import math

import numpy as np

from radfield.core.geometry.cameras import Camera
from radfield.demo.scenes import Lighting, PointLight, Scene


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
                rng: np.random.Generator | None = None, deform=None,
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
