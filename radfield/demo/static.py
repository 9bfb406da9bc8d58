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
from pathlib import Path

import numpy as np

from radfield.core.geometry.cameras import Camera, opencv_to_opengl
from radfield.demo.deformations import Deformation, get_deformation
from radfield.demo.raytrace import render_view
from radfield.demo.scenes import CAMERA_ANGLE_X, CAMERA_RADIUS, Scene, get_scene, orbit_cameras
from radfield.errors import RadfieldError
from radfield.util.atomic import new_folder
from radfield.datasets.images import write_image


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


def write(name: str, folder: Path, *, train_views: int | None = None, test_views: int | None = None, size: int = 64,
          seed: int = 0, quiet: bool = True, deform: str | None = None, workers: int = 1) -> str:
    """The static family's writer (radfield.demo): `generate_scene`, and what it wrote in one line."""
    generate_scene(name, folder, n_train=train_views, n_test=test_views, size=size, seed=seed, deform=deform,
                   workers=workers)
    train, test = (len(json.loads((folder / f"transforms_{split}.json").read_text())["frames"]) for split in ("train", "test"))
    what = name if deform is None else f"{name} deformed by {deform} (edit spec: {folder / 'deform.yaml'})"
    return f"wrote {what}: {train} train + {test} test views of {size}x{size} to {folder}"
