"""Camera paths for `radfield render` and `radfield animate`: a turntable orbit, a nerfstudio
camera-path JSON, and writing frames to an MP4 (imageio-ffmpeg ships its own ffmpeg).

Orbit: cameras on a circle of `radius` around `target`, `elevation` degrees above the plane
perpendicular to `up`, starting at `start` degrees and turning once over `frames` frames, all
looking at the target. Defaults come from a dataset's cameras (`orbit_from_cameras`): the target
is the point nearest to every camera's optical axis (least squares), the radius the median
distance of the cameras to it, `up` the mean camera up vector, the intrinsics the first camera's.

nerfstudio camera path (the viewer's "export path"): {"render_width", "render_height",
"camera_path": [{"camera_to_world": 16 numbers, row-major 4×4, OpenGL axes, "fov": vertical
degrees, "aspect"}], "fps"}. Poses are taken in the dataset's world frame.
"""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import torch

from radfield.util.atomic import atomic_write
from radfield.core.geometry.cameras import Camera, look_at, opengl_to_opencv
from radfield.errors import RadfieldError


def fibonacci_directions(n: int) -> np.ndarray:
    """`n` unit vectors (n, 3) spread evenly over the sphere: the golden-angle (Fibonacci) spiral,
    uniform in height z = 1 − 2(k + ½)/n, so never exactly at a pole."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def orbit(target, radius: float, elevation: float, frames: int, template: Camera, up=(0.0, 0.0, 1.0),
          start: float = 0.0) -> list[Camera]:
    """`frames` cameras (intrinsics of `template`) turning once around `target` (module docstring)."""
    if frames < 1 or not radius > 0:
        raise RadfieldError(f"orbit: need frames >= 1 and a positive radius, got {frames} and {radius}")
    up = np.asarray(up, np.float64)
    up = up / np.linalg.norm(up)
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    target = np.asarray(target, np.float64)
    el = math.radians(elevation)
    cams = []
    for i in range(frames):
        az = math.radians(start) + 2 * math.pi * i / frames
        eye = target + radius * (math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(el) * up)
        c2w = look_at(eye, target, up)
        cams.append(Camera(template.fx, template.fy, template.cx, template.cy, template.width, template.height,
                           c2w, name=f"orbit_{i:04d}"))
    return cams


def orbit_from_cameras(cameras: list[Camera]) -> dict:
    """Default orbit parameters (target, radius, up) from a dataset's cameras."""
    centres = np.stack([c.c2w[:3, 3].numpy() for c in cameras])
    axes = np.stack([c.c2w[:3, 2].numpy() for c in cameras])
    # the point nearest to every optical axis: Σ (I − d dᵀ)(p − o) = 0
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    lhs, rhs = proj.sum(0), np.einsum("nij,nj->i", proj, centres)
    target = np.linalg.lstsq(lhs, rhs, rcond=None)[0] if np.linalg.matrix_rank(lhs) == 3 else centres.mean(0)
    up = -np.stack([c.c2w[:3, 1].numpy() for c in cameras]).mean(0)   # OpenCV: image y points down
    up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-6 else np.array([0.0, 0.0, 1.0])
    return {"target": target, "radius": float(np.median(np.linalg.norm(centres - target, axis=1))), "up": up}


def read_nerfstudio_path(path: str | Path) -> tuple[list[Camera], float | None]:
    """Cameras of a nerfstudio camera-path JSON (module docstring) and its fps (None if absent)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        width, height = int(data["render_width"]), int(data["render_height"])
        entries = data["camera_path"]
        cams = []
        for i, entry in enumerate(entries):
            c2w_gl = torch.tensor(entry["camera_to_world"], dtype=torch.float64).reshape(4, 4)
            fov = float(entry["fov"])
            if not 0 < fov < 180:
                raise ValueError(f"camera_path[{i}].fov must be in (0, 180) degrees, got {fov}")
            fy = 0.5 * height / math.tan(math.radians(fov) / 2)
            cams.append(Camera(fy, fy, width / 2, height / 2, width, height, opengl_to_opencv(c2w_gl), name=f"path_{i:04d}"))
    except OSError as exc:
        raise RadfieldError(f"{path}: cannot read the camera path ({exc.strerror})") from None
    except (ValueError, KeyError, TypeError, RuntimeError) as exc:
        raise RadfieldError(f"{path}: not a nerfstudio camera path ({type(exc).__name__}: {exc})") from None
    if not cams:
        raise RadfieldError(f"{path}: the camera path is empty")
    fps = data.get("fps")
    return cams, float(fps) if isinstance(fps, (int, float)) and fps > 0 else None


def write_video(path: str | Path, frames, fps: float = 30.0) -> None:
    """Write frames (an iterable of (H, W, 3) float arrays in [0, 1] or uint8) to an H.264 MP4
    through imageio-ffmpeg's bundled ffmpeg, atomically (temporary name, then rename)."""
    import imageio_ffmpeg

    frames = iter(frames)
    first = next(frames, None)
    if first is None:
        raise RadfieldError(f"{path}: no frames to write")

    def write(tmp: Path) -> None:
        writer = None
        try:
            for frame in itertools.chain([first], frames):
                frame = np.asarray(frame)
                if frame.dtype != np.uint8:
                    frame = (np.clip(frame, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
                if frame.shape[0] % 2 or frame.shape[1] % 2:   # yuv420p needs even sizes: pad an edge pixel
                    frame = np.pad(frame, ((0, frame.shape[0] % 2), (0, frame.shape[1] % 2), (0, 0)), mode="edge")
                if writer is None:
                    writer = imageio_ffmpeg.write_frames(str(tmp), (frame.shape[1], frame.shape[0]), fps=fps,
                                                         codec="libx264", quality=8, macro_block_size=1,
                                                         pix_fmt_out="yuv420p")
                    writer.send(None)
                writer.send(np.ascontiguousarray(frame[..., :3]))
        finally:
            if writer is not None:
                writer.close()

    atomic_write(path, write)
