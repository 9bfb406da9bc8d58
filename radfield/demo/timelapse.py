"""The dynamic demo scenes (`radfield demo-scene smoke|moving`): every camera photographs the scene
at every time, written as a D-NeRF dataset (the NeRF-synthetic layout whose frames carry a `time`):

    transforms_train.json, transforms_test.json   camera_angle_x; per frame file_path, time, transform_matrix
    train/r_CCC_tTTT.png, test/r_CCC_tTTT.png     camera CCC at time index TTT: RGBA, transparent background
    scene.json                                    name, seed, times, the rig and the scene's own description

Cameras are scenes.orbit_cameras' spiral over the upper hemisphere (36 train + 4 test by
default: the paper's 40-camera setup); times are k / (N − 1), k = 0 … N − 1 (N = 24 by default).
With `held_out_times` the test cameras photograph the N − 1 midpoints (k + ½) / (N − 1) instead,
so no test time is a training time: interpolation in time is measured, not only new views.
Each scene is a module with a `render(camera, ξ)` giving premultiplied RGBA and a `describe()`:
smoke.py (a heterogeneous volume) and moving.py (opaque objects that move and turn).
"""

from __future__ import annotations

import importlib
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from radfield.errors import RadfieldError
from radfield.util.atomic import new_folder

if TYPE_CHECKING:  # light to import: `radfield demo-scene --help` names SCENES without torch
    from radfield.core.geometry.cameras import Camera

TRAIN_VIEWS, TEST_VIEWS, TIMES = 36, 4, 24
# name -> the module that renders it (imported when used: torch for smoke)
SCENES = {"smoke": "radfield.demo.smoke", "moving": "radfield.demo.moving"}


def moments(count: int) -> list[float]:
    """The times photographed: k / (count − 1), k = 0 … count − 1 (0 alone for one)."""
    return [0.0] if count == 1 else [k / (count - 1) for k in range(count)]


def midpoints(count: int) -> list[float]:
    """The held-out times between `count` moments: (k + ½) / (count − 1), k = 0 … count − 2."""
    return [(k + 0.5) / (count - 1) for k in range(count - 1)]


def generate_dynamic(name: str, out_dir: str | os.PathLike, n_train: int | None = None, n_test: int | None = None,
                     times: int | None = None, size: int = 64, seed: int = 0,
                     progress: Callable[[int], None] | None = None, held_out_times: bool = False) -> Path:
    """Write the dynamic scene `name` into a new D-NeRF folder `out_dir` (see the module
    docstring); `progress(1)` after each image; `held_out_times`: test frames at the midpoints.
    Written to a temporary sibling folder and renamed, so `out_dir` is complete or absent; an
    existing non-empty `out_dir` is refused."""
    from radfield.demo.scenes import CAMERA_ANGLE_X, CAMERA_RADIUS, check_counts, orbit_cameras

    if name not in SCENES:
        raise RadfieldError(f"unknown dynamic scene {name!r} (available: {', '.join(SCENES)})")
    scene = importlib.import_module(SCENES[name])
    n_train = TRAIN_VIEWS if n_train is None else n_train
    n_test = TEST_VIEWS if n_test is None else n_test
    times = TIMES if times is None else times
    check_counts(name, n_train, n_test, times, "1 time", size)
    if held_out_times and times < 2:
        raise RadfieldError(f"demo-scene {name}: --held-out-times needs at least 2 times (got {times})")
    out_dir = Path(out_dir)
    with new_folder(out_dir) as tmp:   # complete or absent (util/atomic.py)
        train, test = orbit_cameras(n_train, n_test, size, seed)
        ts = moments(times)
        test_ts = midpoints(times) if held_out_times else ts
        for split, cameras, split_ts in (("train", train, ts), ("test", test, test_ts)):
            _write_split(scene.render, tmp, split, cameras, split_ts, progress)
        held_out = {"test_times": test_ts} if held_out_times else {}
        description = {"name": name, "seed": seed, "times": ts, **held_out, "camera_radius": CAMERA_RADIUS,
                       "camera_angle_x": CAMERA_ANGLE_X, **scene.describe()}
        (tmp / "scene.json").write_text(json.dumps(description, indent=2))
    return out_dir


def _write_split(render: Callable, root: Path, split: str, cameras: list[Camera], ts: list[float],
                 progress: Callable[[int], None] | None) -> None:
    from radfield.core.geometry.cameras import opencv_to_opengl
    from radfield.datasets.images import write_image
    from radfield.demo.scenes import CAMERA_ANGLE_X

    (root / split).mkdir()
    frames = []
    for m, camera in enumerate(cameras):
        for k, xi in enumerate(ts):
            name = f"r_{m:03d}_t{k:03d}"
            write_image(root / split / f"{name}.png", render(camera, xi))
            frames.append({"file_path": f"./{split}/{name}", "time": xi,
                           "transform_matrix": opencv_to_opengl(camera.c2w).tolist()})
            if progress is not None:
                progress(1)
    meta = {"camera_angle_x": CAMERA_ANGLE_X, "frames": frames}
    (root / f"transforms_{split}.json").write_text(json.dumps(meta, indent=2))


def write(name: str, folder: Path, *, train_views: int | None = None, test_views: int | None = None, size: int = 64,
          seed: int = 0, quiet: bool = True, times: int | None = None, held_out_times: bool = False) -> str:
    """The dynamic family's writer (radfield.demo): `generate_dynamic` with a progress bar, and what
    it wrote in one line."""
    from radfield.util.progress import progress_bar

    n_train = TRAIN_VIEWS if train_views is None else train_views
    n_test = TEST_VIEWS if test_views is None else test_views
    count = TIMES if times is None else times
    test_count = count - 1 if held_out_times else count
    with progress_bar(quiet) as progress:
        task = progress.add_task(f"rendering {name}", total=max(0, n_train * count + n_test * test_count))
        generate_dynamic(name, folder, n_train, n_test, count, size, seed, progress=lambda done: progress.advance(task, done),
                         held_out_times=held_out_times)
    between = f" (test at the {test_count} times between)" if held_out_times else ""
    return (f"wrote {name}: {n_train} train + {n_test} test cameras at {count} times{between} "
            f"({n_train * count} + {n_test * test_count} frames) of {size}x{size} to {folder}")
