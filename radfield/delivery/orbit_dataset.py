"""A model's own renders as a posed dataset: what `radfield import` gives a model that came without
one (no photos, no cameras), so that every stage and command that reads a dataset reads these.

`write_orbit_dataset(prims, folder, views, test_views, size)` writes a NeRF-synthetic folder:

    transforms_train.json, transforms_test.json   camera_angle_x + OpenGL camera-to-world per frame
    train/r_i.png, test/r_i.png                   RGBA, 16 bits a channel: the colour C the model
                                                  composites and its opacity α = 1 − T

so that a reader compositing an image over a background b gets C + (1 − α) b, the model rendered
over b (to 16-bit quantisation; a PNG stores C/α, so a mean colour above 1 is clipped there). The cameras look at the model's bounds (`model_bounds`)
from a golden-angle (Fibonacci) spiral over the whole sphere, far enough for the bounding sphere
to fill CAMERA_ANGLE of the view, the test views spread through the spiral.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from radfield.core.geometry.camera_path import fibonacci_directions
from radfield.core.geometry.cameras import Camera, look_at, opencv_to_opengl
from radfield.core.render.antialias import render_model
from radfield.datasets.images import write_image

CAMERA_ANGLE = math.radians(50.0)   # horizontal field of view of every camera
MARGIN = 1.15                       # the bounding sphere fills 1/MARGIN of the view's half-width
OPAQUE_ENOUGH = 0.05                # Gaussians fainter than this opacity do not set the bounds
BOUNDS_QUANTILE = 0.002             # the bounds leave out this fraction of centres on each side (floaters)


def model_bounds(prims) -> tuple[np.ndarray, float]:
    """Centre (3,) and radius of the sphere about the model: the box of its centres between the
    BOUNDS_QUANTILE and 1 − BOUNDS_QUANTILE quantiles per axis (Gaussians fainter than
    OPAQUE_ENOUGH left out), grown by the primitives' typical size."""
    means = prims.means.detach().double()
    opacities = getattr(prims, "opacities", None)
    if opacities is not None:
        seen = torch.sigmoid(opacities.detach().double()) >= OPAQUE_ENOUGH
        means = means[seen] if int(seen.sum()) >= 4 else means
    lo = torch.quantile(means, BOUNDS_QUANTILE, dim=0) if len(means) > 1 else means[0]
    hi = torch.quantile(means, 1 - BOUNDS_QUANTILE, dim=0) if len(means) > 1 else means[0]
    size = float(torch.exp(prims.log_scales.detach().double()).max(1).values.median()) * 3.0
    centre = ((lo + hi) / 2).numpy()
    radius = float(torch.linalg.norm(hi - lo)) / 2 + size
    return centre, max(radius, 1e-6)


def orbit_cameras(centre: np.ndarray, radius: float, views: int, test_views: int, size: int
                  ) -> tuple[list[Camera], list[Camera]]:
    """Train and test cameras (size × size pixels) on a Fibonacci spiral over the whole sphere about
    `centre`, looking at it (+z up), the sphere of `radius` filling the view (module docstring)."""
    n = views + test_views
    directions = fibonacci_directions(n)
    distance = MARGIN * radius / math.sin(CAMERA_ANGLE / 2)
    eyes = np.asarray(centre) + distance * directions
    is_test = np.zeros(n, dtype=bool)
    is_test[np.round(np.linspace(0, n - 1, test_views)).astype(int)] = True
    focal = 0.5 * size / math.tan(CAMERA_ANGLE / 2)

    def camera(index: int, name: str) -> Camera:
        # look_at's up must not be the viewing direction: near the poles +y serves
        up = (0, 0, 1) if abs(directions[index, 2]) < 0.99 else (0, 1, 0)
        return Camera(focal, focal, size / 2, size / 2, size, size, look_at(eyes[index], centre, up), name)

    train = [camera(i, f"r_{m}") for m, i in enumerate(np.flatnonzero(~is_test))]
    test = [camera(i, f"r_{m}") for m, i in enumerate(np.flatnonzero(is_test))]
    return train, test


def write_orbit_dataset(prims, folder: Path, views: int, test_views: int, size: int, near: float = 0.01,
                        on_view: Callable[[], None] | None = None) -> dict:
    """Render `prims` (a static model) from the orbit about its bounds into `folder` (module
    docstring); on_view() after each image. Returns the figures: views, test views, size, the
    bounds' centre and radius."""
    centre, radius = model_bounds(prims)
    splits = dict(zip(("train", "test"), orbit_cameras(centre, radius, views, test_views, size)))
    black = (0.0, 0.0, 0.0)
    for split, cameras in splits.items():
        (folder / split).mkdir(parents=True)
        frames = []
        for camera in cameras:
            with torch.no_grad():
                out = render_model(prims, camera, background=black, near=near)   # colour premultiplied by α
            rgba = torch.cat([out.color, out.alpha[..., None]], -1).numpy()   # premultiplied, as write_image takes it
            write_image(folder / split / f"{camera.name}.png", rgba, bits=16)
            frames.append({"file_path": f"./{split}/{camera.name}",
                           "transform_matrix": opencv_to_opengl(camera.c2w).tolist()})
            if on_view is not None:
                on_view()
        meta = {"camera_angle_x": CAMERA_ANGLE, "frames": frames}
        (folder / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1) + "\n")
    return {"views": views, "test_views": test_views, "size": size,
            "centre": [round(float(c), 6) for c in centre], "radius": round(radius, 6)}
