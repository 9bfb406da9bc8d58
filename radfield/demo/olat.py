"""`radfield demo-scene olat` and `olat-glossy`: the objects of a synthetic scene lit by one point
light at a time, a new light position in every frame (shadows and highlights that move with the
light), ray traced exactly (raytrace.render_view with a scenes.PointLight), written as a
one-light-at-a-time dataset: the NeRF-synthetic layout whose frames carry `light_position` and
`light_intensity` (datasets/transforms.py). SCENES names them, each with the synthetic scene it
lights (its `base`, recorded in scene.json):

    olat          the `studio` objects on their round plinth (moderate highlights, shininess 12-30)
    olat-glossy   the `glossy` objects on their matte slab with sharper, stronger highlights (the
                  spheres at specular 0.7 and 0.6, shininess 40 and 80: a lobe of 13-18 degrees
                  that moves with the light) and the thin rod made a tall matte pillar (radius
                  0.12, 0.99 high: 5 px wide at 64 px) whose shadow sweeps over the slab as the
                  light circles

Both are written the same way:

    transforms_train.json, transforms_test.json   camera_angle_x; per frame file_path, transform_matrix,
                                                  light_position, light_intensity
    train/r_CCC_lLL.png, test/r_CCC_lLL.png       camera CCC under its LL-th light: RGBA, transparent background
    mesh.ply                                      the objects triangulated (the object's bounds, and init)
    scene.json                                    name, base, seed, the light rig, the shading and the shapes

Cameras: scenes.orbit_cameras' spiral (40 train + 8 test by default); each photographs the
object under `lights` (5) point lights, as OLAT captures repeat a camera under many lights, so
200 train and 40 test frames. Lights: one golden-angle spiral of (train + test cameras) × lights
points on a sphere of radius LIGHT_RADIUS (2.5× studio's bounding radius of 1.1, 2.1× glossy's
1.3: one rig for both) about the origin, from just below the plinth's or slab's top (sin
elevation −0.1) to near the zenith (0.95): mostly the upper hemisphere. The test lights are
interleaved in the spiral, so every frame has its own light and no test light is a training one;
camera c of a split takes that split's lights c, c + cameras, c + 2·cameras, …, so each camera
sees lights from low and high.

Shading (raytrace.shade): Lambert + Blinn-Phong highlights of the scene's materials, under the
point light's irradiance intensity / r² with hard shadows (a shadow ray to the point), plus the
base scene's ambient term (studio's sky dome; glossy's is constant) at AMBIENT = 0.2 (the studio's
0.5 would leave shadows half lit: 0.2 keeps 80% of a lit surface's diffuse light with the point
light, so shadows are deep, while faces turned away from it stay visible). intensity =
LIGHT_RADIUS², so a surface facing the light at the origin gets the irradiance of the other demo
scenes' distant light. 4×4 jittered rays per pixel, one pattern per camera (drawn from (seed,
split, camera)), the same under each of its lights.
"""

from __future__ import annotations

import dataclasses
import json
import os
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from radfield.core.geometry.cameras import Camera, opencv_to_opengl
from radfield.datasets.images import write_image
from radfield.demo.shapes import Cylinder, Material
from radfield.demo.scenes import (CAMERA_ANGLE_X, CAMERA_RADIUS, Lighting, PointLight, Scene, check_counts, get_scene,
                                  orbit_cameras)
from radfield.demo.raytrace import render_view
from radfield.demo.static import write_mesh
from radfield.errors import RadfieldError
from radfield.util.atomic import new_folder

TRAIN_VIEWS, TEST_VIEWS, LIGHTS = 40, 8, 5   # cameras per split, lights per camera
LIGHT_RADIUS = 2.75
AMBIENT = 0.2
SAMPLES = 4
_LIGHT_ELEVATION_SIN = (-0.1, 0.95)
PILLAR_RADIUS, PILLAR_TOP = 0.12, 0.6   # olat-glossy's pillar (see _glossy_with_pillar)


def _glossy_with_pillar(glossy: tuple) -> tuple:
    """olat-glossy's objects: glossy's, with both spheres' highlights strong (specular 0.7 and 0.6,
    their shininess 40 and 80 kept: sharp) and the thin rod (3 px, mildly glossy) made a tall matte
    pillar, so that its cast shadow on the matte slab is wide enough to see and to learn."""
    slab, red, blue, box, torus, rod = glossy
    return (slab,
            dataclasses.replace(red, material=dataclasses.replace(red.material, specular=0.7)),
            dataclasses.replace(blue, material=dataclasses.replace(blue.material, specular=0.6)),
            box, torus,
            Cylinder(rod.start, (rod.start[0], rod.start[1], PILLAR_TOP), PILLAR_RADIUS, Material((0.85, 0.85, 0.85))))


@dataclasses.dataclass(frozen=True)
class OlatRecipe:
    """An OLAT demo scene: the synthetic scene whose objects it lights (`base`), what it shows,
    and how its objects derive from the base's (None: the base's own)."""

    base: str
    description: str
    objects: Callable[[tuple], tuple] | None = None


# the one place that names the OLAT demo scenes (`radfield demo-scene NAME`)
SCENES: dict[str, OlatRecipe] = {
    "olat": OlatRecipe("studio", "the studio objects lit by one point light at a time, a new light in every frame"),
    "olat-glossy": OlatRecipe(
        "glossy", "glossy objects with sharp highlights and a tall pillar casting its shadow on a matte slab, "
                  "lit by one point light at a time, a new light in every frame", _glossy_with_pillar),
}


def olat_scene(name: str = "olat") -> Scene:
    """The OLAT scene `name`: its base scene's objects (as its recipe derives them), shaded for
    point lights (see the module docstring)."""
    if name not in SCENES:
        raise RadfieldError(f"unknown olat scene {name!r} (available: {', '.join(SCENES)})")
    recipe = SCENES[name]
    base = get_scene(recipe.base)
    primitives = base.primitives if recipe.objects is None else recipe.objects(base.primitives)
    # jittered samples: one pattern per camera, the same under each of its lights (_write_split)
    return dataclasses.replace(
        base, name=name, samples=SAMPLES, jitter=True, description=recipe.description, primitives=primitives,
        lighting=Lighting(ambient=AMBIENT, shadows=True, sky=base.lighting.sky))


def light_spiral(count: int, seed: int = 0) -> np.ndarray:
    """`count` points (count, 3) on a golden-angle spiral over the light sphere (radius LIGHT_RADIUS,
    sin elevation from −0.1 to 0.95, low to high); the seed turns the spiral."""
    k = np.arange(count)
    z = _LIGHT_ELEVATION_SIN[0] + (_LIGHT_ELEVATION_SIN[1] - _LIGHT_ELEVATION_SIN[0]) * (k + 0.5) / count
    # another turn than the cameras' spiral, so lights do not line up with cameras
    azimuth = np.random.default_rng([seed, 1]).uniform(0, 2 * math.pi) + k * math.pi * (3 - math.sqrt(5))
    ring = np.sqrt(1 - z**2)
    return LIGHT_RADIUS * np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z], -1)


def split_lights(n_train: int, n_test: int, lights: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The train (n_train·lights, 3) and test (n_test·lights, 3) light positions: one spiral, the
    test ones spread evenly through it (so over all heights), never on a train light."""
    points = light_spiral((n_train + n_test) * lights, seed)
    n_test_lights = n_test * lights
    is_test = np.zeros(len(points), dtype=bool)
    is_test[np.round(np.linspace(0, len(points) - 1, n_test_lights)).astype(int)] = True
    return points[~is_test], points[is_test]


def generate_olat(out_dir: str | os.PathLike, n_train: int | None = None, n_test: int | None = None,
                  lights: int | None = None, size: int = 64, seed: int = 0, mesh: bool = True,
                  progress: Callable[[int], None] | None = None, name: str = "olat") -> Path:
    """Write the OLAT scene `name` into a new folder `out_dir` (see the module docstring): n_train
    and n_test cameras, each under `lights` point lights; `progress(1)` after each image. mesh=False
    leaves out mesh.ply (its writer needs pyvista). Written to a temporary sibling folder and
    renamed, so `out_dir` is complete or absent; an existing non-empty `out_dir` is refused."""
    n_train = TRAIN_VIEWS if n_train is None else n_train
    n_test = TEST_VIEWS if n_test is None else n_test
    lights = LIGHTS if lights is None else lights
    check_counts(name, n_train, n_test, lights, "1 light per camera", size)
    scene = olat_scene(name)
    out_dir = Path(out_dir)
    with new_folder(out_dir) as tmp:   # complete or absent (util/atomic.py)
        cameras = orbit_cameras(n_train, n_test, size, seed)
        for split, split_cameras, positions in zip(("train", "test"), cameras, split_lights(n_train, n_test, lights, seed)):
            _write_split(scene, tmp, split, split_cameras, positions, seed, progress)
        if mesh:
            write_mesh(scene, tmp / "mesh.ply")
        (tmp / "scene.json").write_text(json.dumps(_describe(scene, seed, lights), indent=2))
    return out_dir


def _write_split(scene: Scene, root: Path, split: str, cameras: list[Camera], positions: np.ndarray, seed: int,
                 progress: Callable[[int], None] | None) -> None:
    (root / split).mkdir()
    frames = []
    intensity = LIGHT_RADIUS**2
    for c, camera in enumerate(cameras):
        for j in range(len(positions) // len(cameras)):
            position = positions[c + j * len(cameras)]   # lights from low and high for every camera
            name = f"r_{c:03d}_l{j:02d}"
            # the camera's own sample pattern under every light: its pixels see the same points
            # (the same silhouette), only the light changes, as in a capture
            rng = np.random.default_rng([seed, ("train", "test").index(split), c])
            rgba, _ = render_view(scene, camera, rng=rng, point_light=PointLight(tuple(position), intensity))
            write_image(root / split / f"{name}.png", rgba)
            frames.append({"file_path": f"./{split}/{name}",
                           "transform_matrix": opencv_to_opengl(camera.c2w).tolist(),
                           "light_position": [float(x) for x in position],
                           "light_intensity": intensity})
            if progress is not None:
                progress(1)
    meta = {"camera_angle_x": CAMERA_ANGLE_X, "frames": frames}
    (root / f"transforms_{split}.json").write_text(json.dumps(meta, indent=2))


def _describe(scene: Scene, seed: int, lights: int) -> dict:
    """scene.json: the base scene, the light rig, the shading and the exact shapes."""
    return {
        "name": scene.name,
        "base": SCENES[scene.name].base,
        "description": scene.description,
        "seed": seed,
        "lights_per_camera": lights,
        "light_radius": LIGHT_RADIUS,
        "light_intensity": LIGHT_RADIUS**2,
        "light_elevation_sin": list(_LIGHT_ELEVATION_SIN),
        "shading": "albedo (ambient(n) + (1 - ambient) max(0, n.l) V I/r^2) + k_s max(0, n.h)^p [n.l > 0] V I/r^2, "
                   "ambient(n) = ambient (1 + sky n_z)/(1 + sky), V a hard shadow ray to the light",
        "lighting": {k: v for k, v in dataclasses.asdict(scene.lighting).items() if k not in ("direction", "radius")},
        "samples_per_pixel": scene.samples**2,
        "jittered": scene.jitter,
        "camera_radius": CAMERA_RADIUS,
        "camera_angle_x": CAMERA_ANGLE_X,
        "primitives": [{"type": type(p).__name__.lower(), **dataclasses.asdict(p)} for p in scene.primitives],
    }


def write(name: str, folder: Path, *, train_views: int | None = None, test_views: int | None = None, size: int = 64,
          seed: int = 0, quiet: bool = True, lights: int | None = None) -> str:
    """The one-light-at-a-time family's writer (radfield.demo): `generate_olat` with a progress bar,
    and what it wrote in one line."""
    from radfield.util.progress import progress_bar

    n_train = TRAIN_VIEWS if train_views is None else train_views
    n_test = TEST_VIEWS if test_views is None else test_views
    count = LIGHTS if lights is None else lights
    with progress_bar(quiet) as progress:
        task = progress.add_task(f"rendering {name}", total=max(0, (n_train + n_test) * count))
        generate_olat(folder, n_train, n_test, count, size, seed, progress=lambda done: progress.advance(task, done),
                      name=name)
    return (f"wrote {name}: {n_train} train + {n_test} test cameras under {count} point lights each, every frame its "
            f"own light ({n_train * count} + {n_test * count} frames) of {size}x{size} to {folder}")
