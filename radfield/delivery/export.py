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
  Other tools draw these with one ray per pixel: a model trained with `render.supersample` = n > 1
  (its pixels the mean of n × n rays, docs/usage.md) cannot be drawn so, and `radfield export` warns
  (`supersample_warning`; a run's refinement fits the Gaussians to the model's n × n renders).
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

import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from radfield import conditions
from radfield.util.atomic import atomic_write, atomic_write_bytes, atomic_write_text
from radfield.core.geometry.cameras import Camera, opencv_to_opengl
from radfield.errors import RadfieldError
from radfield.core import kinds
from radfield.core.kinds.gaussian import Gaussians
from radfield.core.splat.sh import C0, num_sh_coeffs

MODEL_FORMATS = ("ply-3dgs", "splat", "points")      # need only a model
RUN_FORMATS = ("cage", "envelope", "cameras")         # need a run's artifacts
FORMATS = MODEL_FORMATS + RUN_FORMATS
SUFFIXES = {"ply-3dgs": (".ply",), "splat": (".splat",), "points": (".ply",), "cage": (".vtk", ".msh"),
            "envelope": (".ply",), "cameras": (".json",)}
REST_COEFFS = num_sh_coeffs(3) - 1  # 15 per channel: the 45 f_rest of a degree-3 3DGS PLY
ONE_RAY_FORMATS = ("ply-3dgs", "splat")  # drawn by other tools with one ray per pixel


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
    (e.g. the number of Gaussians written)."""
    path = check_target(format, path)
    if format == "ply-3dgs":
        gaussians = as_gaussians(content.model, components)
        atomic_write_bytes(path, gaussian_ply_bytes(gaussians))
        return {"gaussians": len(gaussians), "from": content.model.kind}
    if format == "splat":
        gaussians = as_gaussians(content.model, components)
        atomic_write_bytes(path, splat_bytes(gaussians))
        return {"gaussians": len(gaussians), "from": content.model.kind}
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


def gaussian_ply_arrays(g: Gaussians) -> dict[str, np.ndarray]:
    """The 3DGS PLY's vertex properties, name -> (P,) float32, in the file's order."""
    n = len(g)
    sh = _cpu(g.sh)                                             # (P, K, 3)
    rest = np.zeros((n, 3, REST_COEFFS), np.float32)
    rest[:, :, : sh.shape[1] - 1] = sh[:, 1:, :].transpose(0, 2, 1)   # channel-major as the 3DGS code
    quats = torch.nn.functional.normalize(g.quats.detach().to("cpu", torch.float64), dim=-1).float().numpy()
    columns = {"x": _cpu(g.means)[:, 0], "y": _cpu(g.means)[:, 1], "z": _cpu(g.means)[:, 2]}
    columns.update({name: np.zeros(n, np.float32) for name in ("nx", "ny", "nz")})
    columns.update({f"f_dc_{c}": sh[:, 0, c] for c in range(3)})
    columns.update({f"f_rest_{i}": col for i, col in enumerate(rest.reshape(n, -1).T)})
    columns["opacity"] = _cpu(g.opacities)
    columns.update({f"scale_{i}": _cpu(g.log_scales)[:, i] for i in range(3)})
    columns.update({f"rot_{i}": quats[:, i] for i in range(4)})
    return columns


def read_gaussian_ply(path: str | Path) -> Gaussians:
    """A 3DGS PLY (this layout, any SH degree 0-3 by its f_rest count) as Gaussians, e.g. to
    measure an export with radfield's renderer."""
    from plyfile import PlyData

    try:
        v = PlyData.read(str(path))["vertex"]
        names = {p.name for p in v.properties}
        n_rest = sum(name.startswith("f_rest_") for name in names)
        col = lambda *keys: torch.from_numpy(np.stack([np.asarray(v[k], np.float32) for k in keys], 1))
        rest = col(*(f"f_rest_{i}" for i in range(n_rest))).reshape(len(v.data), 3, n_rest // 3).transpose(1, 2)
        sh = torch.cat([col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :], rest], 1)
        g = Gaussians(means=col("x", "y", "z"), log_scales=col("scale_0", "scale_1", "scale_2"),
                      quats=col("rot_0", "rot_1", "rot_2", "rot_3"), sh=sh, opacities=col("opacity")[:, 0])
        g.sh_degree  # (K must be (degree + 1)², degree ≤ 3)
    except (OSError, ValueError, KeyError) as error:
        raise RadfieldError(f"{path}: not a readable 3DGS PLY ({error})") from None
    return g


def _ply_bytes(elements) -> bytes:
    from plyfile import PlyData

    buffer = io.BytesIO()
    PlyData(elements, text=False, byte_order="<").write(buffer)
    return buffer.getvalue()


def _vertex_element(columns: dict[str, np.ndarray], name: str = "vertex"):
    from plyfile import PlyElement

    first = next(iter(columns.values()))
    table = np.empty(len(first), dtype=[(key, col.dtype.str) for key, col in columns.items()])
    for key, col in columns.items():
        table[key] = col
    return PlyElement.describe(table, name)


def gaussian_ply_bytes(g: Gaussians) -> bytes:
    return _ply_bytes([_vertex_element(gaussian_ply_arrays(g))])


def splat_bytes(g: Gaussians) -> bytes:
    """antimatter15 .splat records (see the module docstring), most important first."""
    means = _cpu(g.means)
    log_scales = _cpu(g.log_scales)
    opacity = 1 / (1 + np.exp(-_cpu(g.opacities).astype(np.float64)))
    order = np.argsort(-np.exp(log_scales.astype(np.float64).sum(-1)) * opacity, kind="stable")
    rgba = np.concatenate([0.5 + C0 * _cpu(g.sh[:, 0, :]), opacity[:, None]], -1)
    quats = _cpu(g.quats).astype(np.float64)
    quats = quats / np.linalg.norm(quats, axis=-1, keepdims=True)
    record = np.empty(len(g), dtype=[("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
    record["position"] = means
    record["scale"] = np.exp(log_scales)
    record["rgba"] = (rgba * 255).clip(0, 255).astype(np.uint8)
    record["rot"] = (quats * 128 + 128).clip(0, 255).astype(np.uint8)
    return record[order].tobytes()


def points_ply_bytes(model: kinds.Primitives) -> bytes:
    """Primitive centres with their SH DC colour (uchar, rounded)."""
    means = _cpu(model.means)
    rgb = np.round(np.clip(0.5 + C0 * _cpu(model.sh[:, 0, :]), 0, 1) * 255).astype(np.uint8)
    columns = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2],
               "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]}
    return _ply_bytes([_vertex_element(columns)])


def mesh_ply_bytes(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    from plyfile import PlyElement

    v = np.asarray(vertices, np.float32)
    face = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = np.asarray(faces, np.int32)
    return _ply_bytes([_vertex_element({"x": v[:, 0], "y": v[:, 1], "z": v[:, 2]}),
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
