"""Pinhole cameras in the OpenCV convention (x right, y down, z forward), camera-to-world 4x4.

Pixel (row i, column j) has its centre at image coordinates (j + 0.5, i + 0.5); the principal
point (cx, cy) is given in the same continuous coordinates, so cx = W/2 is the image centre.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import torch

from radfield.errors import RadfieldError

# OpenGL/NeRF camera axes (x right, y up, looking down -z) -> OpenCV axes: flip y and z.
_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


@dataclass(frozen=True)
class Light:
    """The light a view was lit by (one-light-at-a-time captures, Splat the Net appendix C.2): a point
    light at `position` (world frame) or a directional light shining along `direction` (unit, from the
    light towards the scene), of known `intensity`: a point light's irradiance falls off as
    intensity / r², a directional light's is the intensity. Relightable kinds read it (kinds:
    PrimitiveKind.at_view); nothing learns it."""

    position: tuple[float, float, float] | None = None
    direction: tuple[float, float, float] | None = None
    intensity: float = 1.0

    def __post_init__(self):
        if (self.position is None) == (self.direction is None):
            raise RadfieldError("a light is a point light (position) or a directional one (direction), one of the two")
        vector = self.position if self.position is not None else self.direction
        if len(vector) != 3 or not all(math.isfinite(float(x)) for x in vector):
            raise RadfieldError(f"a light's position or direction must be three finite numbers, got {vector!r}")
        if not (math.isfinite(self.intensity) and self.intensity > 0):
            raise RadfieldError(f"a light's intensity must be a positive number, got {self.intensity!r}")
        if self.direction is not None:
            norm = math.sqrt(sum(float(x) ** 2 for x in self.direction))
            if norm == 0:
                raise RadfieldError("a directional light needs a non-zero direction")
            object.__setattr__(self, "direction", tuple(float(x) / norm for x in self.direction))
        else:
            object.__setattr__(self, "position", tuple(float(x) for x in self.position))


@dataclass(frozen=True)
class Camera:
    """One pinhole view. `c2w` is a 4x4 camera-to-world matrix (OpenCV axes), float64 on the CPU
    so that conversions stay exact; the renderer casts it to the working dtype and device."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    c2w: torch.Tensor
    name: str = ""
    # what the view carries besides its pose, by condition name (radfield/conditions: "time", the
    # moment ξ_t in [0, 1] it shows; "light", the Light it is lit by); empty for a static scene
    # under fixed lighting. A kind conditioned on one reads it (kinds: PrimitiveKind.at_view).
    conditions: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        c2w = torch.as_tensor(self.c2w, dtype=torch.float64).cpu()
        if c2w.shape != (4, 4) or not torch.isfinite(c2w).all():
            raise RadfieldError(f"camera {self.name!r}: camera-to-world must be a finite 4x4 matrix")
        if self.width <= 0 or self.height <= 0 or self.fx <= 0 or self.fy <= 0:
            raise RadfieldError(f"camera {self.name!r}: width, height and focal lengths must be positive")
        object.__setattr__(self, "c2w", c2w)

    def at(self, **values: Any) -> "Camera":
        """The same view carrying these condition values (`camera.at(time=0.5)`; None drops one)."""
        conditions = {**self.conditions, **values}
        return replace(self, conditions={k: v for k, v in conditions.items() if v is not None})

    @property
    def K(self) -> torch.Tensor:
        return torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=torch.float64)

    @property
    def w2c(self) -> torch.Tensor:
        return torch.linalg.inv(self.c2w)

    @property
    def center(self) -> torch.Tensor:
        return self.c2w[:3, 3]

    def scaled(self, factor: float) -> "Camera":
        """The same view at `factor` times the resolution (factor 0.5 halves width and height)."""
        w, h = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=w, height=h)


def distinct_poses(cameras: list[Camera]) -> tuple[list[Camera], list[int]]:
    """Each pose of `cameras` once, in the order first seen, without their conditions (views that
    differ only by the moment or the light they show are one pose: a dynamic or relighting
    dataset's camera at each of its moments or lights); and for each camera the index of its pose."""
    poses: dict[tuple, int] = {}
    firsts: list[Camera] = []
    index = []
    for camera in cameras:
        key = (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, camera.c2w.numpy().tobytes())
        if key not in poses:
            poses[key] = len(firsts)
            firsts.append(replace(camera, conditions={}))
        index.append(poses[key])
    return firsts, index


def axes_half_angle(cameras: list[Camera]) -> float:
    """The half-angle (degrees) of the cone about their mean direction that holds every camera's
    optical axis: a few degrees for a forward-facing capture (LLFF's), 90 or more for views around
    an object."""
    axes = torch.stack([camera.c2w[:3, 2] for camera in cameras])   # OpenCV: +z looks forward
    mean = torch.nn.functional.normalize(axes.sum(0), dim=0)
    return math.degrees(math.acos(float((axes @ mean).min().clamp(-1.0, 1.0))))


def opengl_to_opencv(c2w_gl: torch.Tensor) -> torch.Tensor:
    """Camera-to-world in OpenGL axes (NeRF-synthetic, nerfstudio) -> OpenCV axes."""
    return torch.as_tensor(c2w_gl, dtype=torch.float64) @ _GL_TO_CV


def opencv_to_opengl(c2w_cv: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(c2w_cv, dtype=torch.float64) @ _GL_TO_CV


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """OpenCV camera-to-world looking from `eye` at `target`, with `up` pointing up in the image."""
    eye, target, up = (torch.as_tensor(v, dtype=torch.float64) for v in (eye, target, up))
    z = torch.nn.functional.normalize(target - eye, dim=0)
    x = torch.nn.functional.normalize(torch.linalg.cross(z, up), dim=0)
    y = torch.linalg.cross(z, x)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return c2w


def pixel_rays(camera: Camera, dtype=torch.float32, device="cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """World-space unit directions (H, W, 3) through every pixel centre, and the per-pixel ray
    distance to the camera-space plane z = 1 (|K^-1 [u, v, 1]|), used to turn z-depths into ray
    distances."""
    j = torch.arange(camera.width, dtype=torch.float64) + 0.5
    i = torch.arange(camera.height, dtype=torch.float64) + 0.5
    ii, jj = torch.meshgrid(i, j, indexing="ij")
    d_cam = torch.stack([(jj - camera.cx) / camera.fx, (ii - camera.cy) / camera.fy, torch.ones_like(ii)], -1)
    norm = d_cam.norm(dim=-1)
    d_world = (d_cam / norm[..., None]) @ camera.c2w[:3, :3].T
    return d_world.to(dtype=dtype, device=device), norm.to(dtype=dtype, device=device)
