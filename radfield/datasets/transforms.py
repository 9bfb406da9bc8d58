"""The `transforms*.json` camera files shared by two formats: NeRF-synthetic
(`transforms_{train,val,test}.json`, formats/nerf_synthetic.py) and nerfstudio / instant-ngp (one
`transforms.json`, formats/nerfstudio.py). This module parses a file and turns its frames into
views; which file holds which split is each format's business.

Both store camera-to-world matrices in OpenGL axes (converted to OpenCV here) and intrinsics at
file level, which nerfstudio lets each frame override. Principal points use the same continuous
pixel coordinates as `Camera` (cx = w/2 is the centre), as instant-ngp and nerfstudio do.
Lens distortion (k1 k2 p1 p2 [k3], OpenCV model) is recorded per view and removed on load.

A frame may carry conditions besides its camera (radfield/conditions: a dynamic dataset's `time`,
a one-light-at-a-time capture's `light_position` or `light_direction`); each registered condition
reads its own keys (`Condition.read_frame`) into the view's `Camera.conditions`. Either every frame
of the dataset carries a condition or none does (`check_frames`), so a scene is wholly static or
wholly dynamic, and each condition checks the views together once every frame read has its camera
(`check_views`: e.g. no point light inside the object's bounds).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from functools import cache
from pathlib import Path

import numpy as np
import torch

from radfield import conditions
from radfield.core.geometry.cameras import Camera, opengl_to_opencv
from radfield.errors import RadfieldError
from radfield.datasets.images import image_size
from radfield.datasets.views import View

# Tried in this order when a `file_path` has no extension (NeRF-synthetic writes `./train/r_0`).
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")
_DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")  # OpenCV order
_PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")


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
    """Every registered condition over the frames of these transforms files (path, content)
    together: a valid value on every frame, or none on any. The first offending frame raises,
    named by file and index."""
    for condition in conditions.registered():
        first = None
        for path, i, frame in _frames(files):
            first = _all_or_none(first, path, i, frame, condition.in_frame(frame), condition)
            condition.read_frame(frame, _where(frame, i, path))   # checks the value


def _frames(files: list[tuple[Path, dict]]):
    """(path, index in its file, frame) of every frame of these transforms files, in order."""
    for path, meta in files:
        for i, frame in enumerate(meta["frames"]):
            yield path, i, frame


def _all_or_none(first, path: Path, i: int, frame: dict, carried: bool, condition):
    """A condition every frame of the files carries or none does: `first` is (path, index, carried)
    of the first frame (None before it), returned for the next frame; a frame that disagrees with it
    raises, naming both frames."""
    if first is None:
        return path, i, carried
    if carried != first[2]:
        what = f"has {condition.frame_words[0]}" if carried else f"has {condition.frame_words[1]}"
        other = "has none" if carried else "has one"
        where = "" if first[0] == path else f" of {first[0]}"
        raise RadfieldError(f"{path}: frames[{i}] ({_frame_name(frame)}) {what} but frames[{first[1]}]{where} "
                            f"{other}: {condition.frame_hint}")
    return first


def _where(frame: dict, i: int, json_path: Path) -> str:
    """frames[i] of a file, for messages."""
    return f"{json_path}: frames[{i}] ({_frame_name(frame)})"


def _frame_name(frame: dict) -> str:
    """The frame's file_path for messages (its own checks come later)."""
    name = frame.get("file_path")
    return name if isinstance(name, str) else "no file_path"


def check_views(placed: list[tuple[Path, int, dict, View]], root: Path) -> None:
    """Each registered condition's check of the views together (`Condition.check_views`, e.g. no
    point light inside the object's bounds: datasets/bounds.py, the box of `root`/mesh.ply, else
    the ball all these views' cameras frame). `placed`: (transforms file, frame index, frame, its
    view) for every frame read. Checked here, once every frame read has its camera, because only
    the cameras (or the mesh) say where the object is, and here the offending frame can still be
    named."""
    from radfield.datasets.bounds import MESH, object_bounds

    bounds = cache(lambda: object_bounds([view.camera for *_, view in placed], root / MESH))
    for condition in conditions.registered():
        carried = [(_where(frame, i, path), view.camera.conditions[condition.name])
                   for path, i, frame, view in placed if condition.name in view.camera.conditions]
        if carried:
            condition.check_views(carried, bounds)


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
    where = _where(frame, i, json_path)
    values = {c.name: value for c in conditions.registered() if (value := c.read_frame(frame, where)) is not None}
    try:
        return Camera(fx, fy, cx, cy, round(w), round(h), c2w, name, values), distortion
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
