"""The `transforms*.json` camera files shared by two formats: NeRF-synthetic
(`transforms_{train,val,test}.json`, formats/nerf_synthetic.py) and nerfstudio / instant-ngp (one
`transforms.json`, formats/nerfstudio.py). This module parses a file and turns its frames into
views; which file holds which split is each format's business.

Both store camera-to-world matrices in OpenGL axes (converted to OpenCV here) and intrinsics at
file level, which nerfstudio lets each frame override. Principal points use the same continuous
pixel coordinates as `Camera` (cx = w/2 is the centre), as instant-ngp and nerfstudio do.
Lens distortion (k1 k2 p1 p2 [k3], OpenCV model) is recorded per view and removed on load.

A dynamic dataset (D-NeRF, nerfstudio with time) gives each frame a `time`, the moment ξ_t in
[0, 1] it shows (Splat the Net appendix C.1); it becomes the view's `Camera.time`. Either every
frame of the dataset carries one or none does (`check_times`), so a scene is wholly static or
wholly dynamic.

A one-light-at-a-time capture (Splat the Net appendix C.2; GS³, Kang et al.) gives each frame the
light it was lit by: `light_position` ([x, y, z], a point light in the world frame of
`transform_matrix`) or `light_direction` ([x, y, z], a directional light, pointing from the light
towards the scene), and optionally `light_intensity` (> 0, default 1). It becomes the view's
`Camera.light`. As with time, every frame of the dataset carries a light or none does
(`check_lights`), and a point light may not sit inside the object's bounds (`check_light_bounds`:
the readers call it once every frame they read has its camera).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from functools import cache
from pathlib import Path

import numpy as np
import torch

from radfield.core.geometry.cameras import Camera, Light, opengl_to_opencv
from radfield.errors import RadfieldError
from radfield.datasets.images import image_size
from radfield.datasets.views import View

# Tried in this order when a `file_path` has no extension (NeRF-synthetic writes `./train/r_0`).
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")
_DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")  # OpenCV order
_PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
_LIGHT_KEYS = ("light_position", "light_direction")  # a frame's light is one of these (+ light_intensity)


def read_json(path: Path) -> dict:
    """A transforms file as a dict with a 'frames' list of objects; errors name the file."""
    if not path.is_file():
        raise RadfieldError(f"file not found: {path}")
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise RadfieldError(f"{path}: invalid JSON ({e.msg} at line {e.lineno} column {e.colno})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise RadfieldError(f"cannot read {path}: {e}") from None
    if not isinstance(meta, dict):
        raise RadfieldError(f"{path}: expected a JSON object at the top level")
    if "frames" not in meta:
        raise RadfieldError(f"{path}: missing key 'frames'")
    if not isinstance(meta["frames"], list) or not all(isinstance(f, dict) for f in meta["frames"]):
        raise RadfieldError(f"{path}: 'frames' must be a list of objects")
    check_frames([(path, meta)])
    return meta


def check_frames(files: list[tuple[Path, dict]]) -> None:
    """What must agree across the frames of these transforms files (path, content) together:
    their times (`check_times`) and their lights (`check_lights`)."""
    check_times(files)
    check_lights(files)


def check_times(files: list[tuple[Path, dict]]) -> None:
    """Every frame's `time` of these transforms files (path, content) together: a number in
    [0, 1] on every frame, or on none. The first offending frame raises, named by file and index."""
    first = None
    for path, i, frame in _frames(files):
        timed = "time" in frame
        if timed:
            _check_time(frame, i, path)
        first = _all_or_none(first, path, i, frame, timed, ("a 'time'", "no 'time'"), "give every frame a time or none")


def _frames(files: list[tuple[Path, dict]]):
    """(path, index in its file, frame) of every frame of these transforms files, in order."""
    for path, meta in files:
        for i, frame in enumerate(meta["frames"]):
            yield path, i, frame


def _all_or_none(first, path: Path, i: int, frame: dict, carried: bool, names: tuple[str, str], hint: str):
    """A property every frame of the files carries or none does: `first` is (path, index, carried) of
    the first frame (None before it), returned for the next frame; a frame that disagrees with it
    raises, naming both frames. names: how the message says the frame has it or not."""
    if first is None:
        return path, i, carried
    if carried != first[2]:
        what = f"has {names[0]}" if carried else f"has {names[1]}"
        other = "has none" if carried else "has one"
        where = "" if first[0] == path else f" of {first[0]}"
        raise RadfieldError(f"{path}: frames[{i}] ({_frame_name(frame)}) {what} but frames[{first[1]}]{where} "
                            f"{other}: {hint}")
    return first


def _check_time(frame: dict, i: int, json_path: Path) -> None:
    value = frame["time"]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise RadfieldError(f"{json_path}: frames[{i}] ({_frame_name(frame)}): 'time' must be a number in [0, 1], "
                            f"not {value!r:.40}")
    if not 0.0 <= value <= 1.0:
        raise RadfieldError(f"{json_path}: frames[{i}] ({_frame_name(frame)}): 'time' {value!r} is outside [0, 1]")


def check_lights(files: list[tuple[Path, dict]]) -> None:
    """Every frame's light of these transforms files (path, content) together: a valid light on
    every frame, or none on any. The first offending frame raises, named by file and index."""
    first = None
    for path, i, frame in _frames(files):
        lit = any(key in frame for key in _LIGHT_KEYS)
        first = _all_or_none(first, path, i, frame, lit, ("a light", "no light"),
                             "give every frame a 'light_position' or 'light_direction', or none")
        frame_light(frame, i, path)  # checks the values (None when the frame has no light)


def frame_light(frame: dict, i: int, json_path: Path) -> Light | None:
    """The Light of frames[i] (None when it has none); a bad one raises naming the file and frame."""
    where = f"{json_path}: frames[{i}] ({_frame_name(frame)})"
    given = [key for key in _LIGHT_KEYS if key in frame]
    if not given:
        if "light_intensity" in frame:
            raise RadfieldError(f"{where}: 'light_intensity' without a 'light_position' or 'light_direction'")
        return None
    if len(given) == 2:
        raise RadfieldError(f"{where}: a light has a 'light_position' (a point light) or a 'light_direction' "
                            "(a directional one), not both")
    key = given[0]
    vector = frame[key]
    if not (isinstance(vector, list) and len(vector) == 3 and all(_is_number(x) for x in vector)):
        raise RadfieldError(f"{where}: '{key}' must be three finite numbers [x, y, z], not {vector!r:.60}")
    if key == "light_direction" and not any(vector):
        raise RadfieldError(f"{where}: 'light_direction' must not be [0, 0, 0]")
    intensity = frame.get("light_intensity", 1.0)
    if not (_is_number(intensity) and intensity > 0):
        raise RadfieldError(f"{where}: 'light_intensity' must be a positive number, not {intensity!r:.40}")
    vector = tuple(float(x) for x in vector)
    if key == "light_position":
        return Light(position=vector, intensity=float(intensity))
    return Light(direction=vector, intensity=float(intensity))


def _is_number(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)


def _frame_name(frame: dict) -> str:
    """The frame's file_path for messages (its own checks come later)."""
    name = frame.get("file_path")
    return name if isinstance(name, str) else "no file_path"


def check_light_bounds(placed: list[tuple[Path, int, dict, View]], root: Path) -> None:
    """No point light of these views inside the object's bounds (datasets/bounds.py: the box of
    `root`/mesh.ply, else the ball all these views' cameras frame). `placed`: (transforms file,
    frame index, frame, its view) for every frame read. Checked here, once every frame read has its
    camera, because only the cameras (or the mesh) say where the object is, and here the offending
    frame can still be named; a light inside the object lights nothing the cameras see, and a
    light given in the wrong units or frame usually lands there."""
    point_lit = [item for item in placed if item[3].camera.light is not None and item[3].camera.light.position is not None]
    if not point_lit:
        return
    from radfield.datasets.bounds import MESH, object_bounds

    bounds = object_bounds([view.camera for *_, view in placed], root / MESH)
    if bounds is None:
        return
    for path, i, frame, view in point_lit:
        position = view.camera.light.position
        if bounds.contains(position):
            raise RadfieldError(f"{path}: frames[{i}] ({_frame_name(frame)}): light_position "
                                f"[{', '.join(f'{x:.4g}' for x in position)}] is inside the object's bounds "
                                f"({bounds.describe()}): a point light must be outside the object")


def placed_views(meta: dict, frames: list[tuple[int, dict]], json_path: Path) -> list[tuple[Path, int, dict, View]]:
    """`frame_views` with where each view came from: (file, frame index, frame, view)."""
    views = frame_views(meta, frames, json_path)
    return [(json_path, i, frame, view) for (i, frame), view in zip(frames, views)]


def frame_views(meta: dict, frames: list[tuple[int, dict]], json_path: Path) -> list[View]:
    """Frames (index in the file, frame) -> views; size falls back to the first image's header."""
    views = []
    first, first_frame = frames[0] if frames else (0, {})
    fallback_size = cache(lambda: image_size(_image_path(first_frame, first, json_path)))
    for i, frame in frames:
        image_path = _image_path(frame, i, json_path)
        camera, distortion = _camera(meta, frame, i, json_path, image_path.stem, fallback_size)
        views.append(View(image_path, camera, distortion))
    return views


def file_path(frame: dict, i: int, json_path: Path) -> str:
    """frames[i].file_path as written (relative to the JSON file's folder)."""
    if "file_path" not in frame:
        raise RadfieldError(f"{json_path}: frames[{i}] is missing key 'file_path'")
    if not isinstance(frame["file_path"], str):
        raise RadfieldError(f"{json_path}: frames[{i}].file_path must be a string")
    return frame["file_path"]


def _image_path(frame: dict, i: int, json_path: Path) -> Path:
    path = json_path.parent / file_path(frame, i, json_path)
    for candidate in (path, *(path.with_name(path.name + suffix) for suffix in _IMAGE_SUFFIXES)):
        if candidate.is_file():
            return candidate
    raise RadfieldError(f"image not found: {path} (frames[{i}].file_path in {json_path})")


def _number(meta: dict, frame: dict, i: int, key: str, json_path: Path) -> float | None:
    """`key` from the frame, else from the file, else None; must be a finite number."""
    value, where = (frame[key], f"frames[{i}].{key}") if key in frame else (meta.get(key), key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise RadfieldError(f"{json_path}: '{where}' must be a finite number, not {value!r:.40}")
    return float(value)


def _camera(
    meta: dict, frame: dict, i: int, json_path: Path, name: str, fallback_size: Callable[[], tuple[int, int]]
) -> tuple[Camera, np.ndarray | None]:
    def get(key):
        return _number(meta, frame, i, key, json_path)

    model = frame.get("camera_model", meta.get("camera_model", "OPENCV"))
    if model not in _PINHOLE_MODELS:
        raise RadfieldError(
            f"{json_path}: camera_model {model!r} is not supported (undistort the images to a pinhole model first)"
        )
    w, h = get("w"), get("h")
    if w is None or h is None:
        w, h = fallback_size()
    fx, fy = get("fl_x"), get("fl_y")
    if fx is None:
        angle = get("camera_angle_x")
        if angle is None:
            raise RadfieldError(f"{json_path}: missing key 'fl_x' (or 'camera_angle_x')")
        fx = 0.5 * w / math.tan(0.5 * angle)
    if fy is None:
        angle = get("camera_angle_y")
        fy = fx if angle is None else 0.5 * h / math.tan(0.5 * angle)
    cx, cy = get("cx"), get("cy")
    cx = w / 2 if cx is None else cx
    cy = h / 2 if cy is None else cy
    if get("k4"):
        raise RadfieldError(f"{json_path}: distortion 'k4' is not supported (fisheye?); undistort the images first")
    coeffs = np.array([get(k) or 0.0 for k in _DISTORTION_KEYS])
    if not coeffs[4]:
        coeffs = coeffs[:4]  # the usual k1 k2 p1 p2
    distortion = coeffs if coeffs.any() else None
    c2w = opengl_to_opencv(_matrix(frame, i, json_path))
    time = None if "time" not in frame else float(frame["time"])  # checked by read_json
    light = frame_light(frame, i, json_path)
    try:
        return Camera(fx, fy, cx, cy, round(w), round(h), c2w, name, time, light), distortion
    except RadfieldError as e:
        raise RadfieldError(f"{json_path}: frames[{i}]: {e}") from None


def _matrix(frame: dict, i: int, json_path: Path) -> torch.Tensor:
    """frames[i].transform_matrix as a float64 4x4 (a 3x4 gets its last row)."""
    if "transform_matrix" not in frame:
        raise RadfieldError(f"{json_path}: frames[{i}] is missing key 'transform_matrix'")
    try:
        m = np.array(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError):
        m = np.empty(0)
    if m.shape not in ((4, 4), (3, 4)) or not np.isfinite(m).all():
        raise RadfieldError(f"{json_path}: frames[{i}].transform_matrix must be a 4x4 matrix of numbers")
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    return torch.from_numpy(m)
