"""Export a model or a run to the file formats other tools read: one function, `export(...)`.

Formats (all in the dataset's world frame):

- ``ply-3dgs``  the 3D-Gaussian PLY of the 3DGS reference code, read by every 3DGS viewer: per
  vertex ``x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2 rot_0..3`` (float32), opacity as
  a logit, log σ scales, w x y z quaternion, ``f_rest`` channel-major (all R coefficients of bands
  1-3, then G, then B; zeros past the model's degree). Gaussians are written exactly; neural
  primitives through their kind (core/kinds/moment_matching.py: `components` Gaussians each; `radfield export`
  then refines them for a run with delivery/refine.py: refine_gaussians and passes Gaussians in).
  A windowed model (prims.window) needs no warning: the moments are those of its windowed density.
- ``splat``     antimatter15's .splat: 32 bytes a splat, position 3×f32, linear σ 3×f32, RGBA 4×u8
  (0.5 + C0·f_dc and sigmoid(opacity), ×255 truncated), rotation 4×u8 ((q/|q|)·128 + 128, w x y z),
  in decreasing order of exp(Σ log σ)·sigmoid(opacity), as that viewer's convert.py writes it.
- ``spz``       Niantic's SPZ version 3: gzip of a 16-byte header and packed arrays (24-bit fixed-point
  positions, 8-bit log scales, alpha and colour, 32-bit smallest-three rotations, 8-bit SH
  quantised to 5 bits in band 1 and 4 bits beyond), in SPZ's RUB axes.
- ``glb``       glTF 2.0 binary with KHR_gaussian_splatting: float32 POSITION, ROTATION (x y z w),
  linear SCALE, OPACITY (sigmoid) and SH_DEGREE_l_COEF_n attributes of a POINTS primitive, in
  glTF's LUF axes.
  These four are written by radfield.model_formats (each module's docstring gives the byte layout
  and what it loses), the same Gaussians in each. Other tools draw them with one ray per pixel: a
  model trained with `render.supersample` = n > 1 (its pixels the mean of n × n rays,
  docs/usage.md) cannot be drawn so, and `radfield export` warns (`supersample_warning`; a run's
  refinement fits the Gaussians to the model's n × n renders).
- ``points``    a PLY point cloud of the primitive centres with uchar ``red green blue`` from SH DC.
- ``cage``      the cage as a tetrahedral mesh, ``.vtk`` (legacy VTK) or ``.msh`` (Gmsh 2.2), meshio.
- ``envelope``  the envelope triangle mesh as a binary PLY.
- ``cameras``   the run's cameras as a nerfstudio ``transforms.json`` (OpenGL axes, per-frame
  intrinsics at the image files' resolution, OpenCV distortion, train/val/test file name lists;
  frames keep their conditions as the readers take them: a dynamic scene's ``time``, a capture's
  ``light_position``).

A conditioned model (a dynamic or relightable kind) is exported under one value of each condition:
`radfield export --time T` hands these functions the static model of that moment
(delivery/content.py: under_conditions).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from radfield import conditions, model_formats
from radfield.util.atomic import atomic_write, atomic_write_bytes, atomic_write_text
from radfield.core.geometry.cameras import Camera, opencv_to_opengl
from radfield.errors import RadfieldError
from radfield.core import kinds
from radfield.core.kinds.gaussian import Gaussians
from radfield.core.splat.sh import C0
from radfield.model_formats.ply_3dgs import ply_bytes, vertex_element

GAUSSIAN_FORMATS = ("ply-3dgs", "splat", "spz", "glb")   # 3D Gaussians, written by radfield.model_formats
MODEL_FORMATS = GAUSSIAN_FORMATS + ("points",)           # need only a model
RUN_FORMATS = ("cage", "envelope", "cameras")            # need a run's artifacts
FORMATS = MODEL_FORMATS + RUN_FORMATS
SUFFIXES = {**{name: model_formats.get(name).suffixes for name in GAUSSIAN_FORMATS},
            "points": (".ply",), "cage": (".vtk", ".msh"), "envelope": (".ply",), "cameras": (".json",)}
ONE_RAY_FORMATS = GAUSSIAN_FORMATS  # drawn by other tools with one ray per pixel


def supersample_warning(model: kinds.Primitives, format: str) -> str | None:
    """One line when `format` cannot hold how the model is drawn (its n × n rays a pixel), else None."""
    n = model.supersample
    if format not in ONE_RAY_FORMATS or n == 1:
        return None
    return (f"radfield: warning: the model was trained with {n}x{n} rays per pixel (render.supersample={n}); "
            f"{format} viewers draw one ray per pixel, so its edges will look harder than in radfield")


@dataclass
class Content:
    """What can be exported: a model, and for a run its cage (V, 3) + (T, 4), envelope (V, 3) +
    (F, 3), its cameras (scene.json's `splits`: split -> list of VIEW dicts), background and extent
    (scene radius, world units). Missing parts are
    None, and `missing` says why (for the error message)."""

    model: kinds.Primitives
    cage: tuple[np.ndarray, np.ndarray] | None = None
    envelope: tuple[np.ndarray, np.ndarray] | None = None
    views: dict[str, list[dict]] | None = None
    background: tuple[float, float, float] | None = None
    extent: float | None = None
    source: str = ""
    missing: dict[str, str] | None = None


def export(content: Content, format: str, path: str | Path, *, components: int = 1) -> dict:
    """Write `content` as `format` to `path` (atomically). Returns figures for the report
    (e.g. the number of Gaussians written and, for the Gaussian formats, the file's bytes)."""
    path = check_target(format, path)
    if format in GAUSSIAN_FORMATS:
        gaussians = as_gaussians(content.model, components)
        figures = model_formats.write(format, gaussians, path)
        return {**figures, "from": content.model.kind}
    if format == "points":
        atomic_write_bytes(path, points_ply_bytes(content.model))
        return {"points": len(content.model)}
    part = {"cage": content.cage, "envelope": content.envelope, "cameras": content.views}[format]
    if part is None:
        why = (content.missing or {}).get(format, "the input is a model file, not a run directory")
        raise RadfieldError(f"{content.source}: cannot export {format}: {why}")
    if format == "cage":
        return write_cage_mesh(path, *part)
    if format == "envelope":
        atomic_write_bytes(path, mesh_ply_bytes(*part))
        return {"vertices": len(part[0]), "faces": len(part[1])}
    frames = nerfstudio_transforms(part)
    atomic_write_text(path, json.dumps(frames, indent=1) + "\n")
    return {"cameras": len(frames["frames"])}


def view_cameras(views: list[dict]) -> list[Camera]:
    """radfield Cameras of scene.json VIEW dicts (posed views only), each with its view's conditions."""
    return [Camera(v["fx"], v["fy"], v["cx"], v["cy"], v["width"], v["height"],
                   torch.tensor(v["c2w"], dtype=torch.float64), v["name"], conditions.view_values(v))
            for v in views if "c2w" in v]


def check_target(format: str, path: str | Path) -> Path:
    """`path` if `format` is known and `path` has a suffix it is written as."""
    path = Path(path)
    if format not in FORMATS:
        raise RadfieldError(f"unknown export format {format!r} (choose one of {', '.join(FORMATS)})")
    if path.suffix.lower() not in SUFFIXES[format]:
        raise RadfieldError(f"{path}: a {format} export is written as {' or '.join(SUFFIXES[format])}")
    return path


def as_gaussians(model: kinds.Primitives, components: int = 1) -> Gaussians:
    """The model as 3D Gaussians, as its kind converts it (radfield.core.kinds: to_gaussians):
    Gaussians as they are, neural primitives moment-matched (`components` Gaussians each)."""
    return kinds.of(model).to_gaussians(model, components)


def _cpu(t: torch.Tensor) -> np.ndarray:
    return t.detach().to("cpu", torch.float32).numpy()


def points_ply_bytes(model: kinds.Primitives) -> bytes:
    """Primitive centres with their SH DC colour (uchar, rounded)."""
    means = _cpu(model.means)
    rgb = np.round(np.clip(0.5 + C0 * _cpu(model.sh[:, 0, :]), 0, 1) * 255).astype(np.uint8)
    columns = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2],
               "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]}
    return ply_bytes([vertex_element(columns)])


def mesh_ply_bytes(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    from plyfile import PlyElement

    v = np.asarray(vertices, np.float32)
    face = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = np.asarray(faces, np.int32)
    return ply_bytes([vertex_element({"x": v[:, 0], "y": v[:, 1], "z": v[:, 2]}),
                       PlyElement.describe(face, "face")])


def write_cage_mesh(path: Path, vertices: np.ndarray, tets: np.ndarray) -> dict:
    import meshio

    tets = np.asarray(tets, np.int64)
    # Gmsh files tag every element with a physical and a geometrical entity: 0 (none)
    tags = {"gmsh:physical": [np.zeros(len(tets), np.int32)], "gmsh:geometrical": [np.zeros(len(tets), np.int32)]}
    mesh = meshio.Mesh(np.asarray(vertices, np.float64), [("tetra", tets)],
                       cell_data=tags if path.suffix.lower() == ".msh" else None)
    file_format = "gmsh22" if path.suffix.lower() == ".msh" else "vtk"
    atomic_write(path, lambda tmp: meshio.write(tmp, mesh, file_format=file_format, binary=file_format == "vtk"))
    return {"vertices": len(mesh.points), "tets": len(tets)}


def nerfstudio_transforms(splits: dict[str, list[dict]]) -> dict:
    """nerfstudio `transforms.json` of scene.json views: OpenGL camera-to-world, intrinsics scaled to
    the image files' resolution (the images file_path points at), split lists by file path."""
    frames, lists = {}, {}
    for split, views in splits.items():
        for view in views:
            if "c2w" not in view:
                raise RadfieldError(f"view {view.get('name')!r} has no pose (the photos were never posed)")
            sx, sy = view["file_width"] / view["width"], view["file_height"] / view["height"]
            frame = {"file_path": str(view["image"]),
                     "transform_matrix": opencv_to_opengl(torch.tensor(view["c2w"], dtype=torch.float64)).tolist(),
                     "fl_x": view["fx"] * sx, "fl_y": view["fy"] * sy, "cx": view["cx"] * sx, "cy": view["cy"] * sy,
                     "w": view["file_width"], "h": view["file_height"]}
            dist = view.get("distortion")
            if dist:
                frame.update(dict(zip(("k1", "k2", "p1", "p2", "k3"), dist)))
            for name, value in conditions.view_values(view).items():   # e.g. a dynamic scene's "time"
                frame.update(conditions.get(name).to_frame(value))
            frames[frame["file_path"]] = frame   # a view in two splits is one frame
            lists.setdefault(f"{split}_filenames", []).append(str(view["image"]))
    return {"camera_model": "OPENCV", "frames": list(frames.values()), **lists}
