"""Stage "envelope" and the coarse envelope: a closed, outward-offset, decimated triangle mesh
that encloses the object.

From points (SfM) or a given mesh: `build_envelope`. From posed silhouettes: `visual_hull`.
`overlay_picture` draws an envelope over one input view so a user can check it.

The stage writes `envelope.ply` and `envelope.png` (the envelope over the first training view)
from, by `envelope.source`: `points` (the SfM points of points.npz), `mesh` (the dataset's
mesh.ply), `hull` (the alpha masks of the training images), `triangulate` (features matched
across the training images, triangulated with their known poses: posed photos without points,
such as a nerfstudio transforms.json), or `auto` (the first of these the dataset has). When `auto`
ends at `triangulate` and too few points come out, the run has no envelope, hence no cage: the
stage says so and is not applicable.

Every envelope goes through the same finish: CGAL alpha wrapping with an offset (pymeshlab
`generate_alpha_wrap`), which gives a watertight, 2-manifold, self-intersection-free surface at the
margin distance outside its input; decimation to the target face count with fast-simplification;
then the checks (watertight, self-intersections, which points lie outside).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
from pathlib import Path
from typing import Any

import cv2
import fast_simplification
import numpy as np
import pymeshlab
import pyvista as pv
from scipy import ndimage
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from radfield.core.atomic import atomic_write
from radfield.core.cameras import Camera
from radfield.core.errors import RadfieldError
from radfield.datasets.views import Dataset
from radfield.stages.config import require
from radfield.stages.data import POINTS, SCENE, load_scene
from radfield.stages.pipeline import Context, NotApplicable, Stage
from radfield.stages.sfm import triangulate

ENVELOPE = "envelope.ply"
OVERLAY = "envelope.png"

# Algorithm constants (the tunable settings are the `envelope` section of pipeline.yaml).
MIN_POINTS = 10  # fewer points make no surface
OUTLIER_NEIGHBORS = 16  # k of both outlier tests
OUTLIER_PROBABILITY = 0.8  # LoOP test: points more likely than this to be outliers are dropped
ALPHA_SHAPE = 0.1  # alpha-shape fallback radius, fraction of the bounding-box diagonal
MAX_OUTSIDE_FRACTION = 0.005  # inlier points allowed outside before trying the next surface
HULL_MIN_VIEWS = 0.5  # visual hull: fraction of the views a voxel must project into
MASK_THRESHOLD = 0.5  # visual hull: alpha above this is foreground

METHODS = ("auto", "poisson", "ball_pivoting", "alpha", "convex")
# Fallback order after the configured surface. Alpha shape and convex hull cannot fail to cover
# the points; the convex hull is the last resort because it fills every concavity.
FALLBACKS = ("alpha", "convex")
# A reconstruction whose box sticks out of the points' box by more than this fraction of the
# diagonal has bulged (screened Poisson closes open scans with large bubbles).
MAX_BULGE = 0.1


def run(ctx: Context) -> dict[str, Any]:
    cfg = ctx.config["envelope"]
    scene = load_scene(ctx.inputs[SCENE])
    with np.load(ctx.inputs[POINTS]) as stored:
        points = {name: stored[name] for name in stored.files}
    train = scene.dataset("train")
    source = choose_source(cfg["source"], points, train)
    if source == "triangulate":
        points["xyz"], _ = triangulate(train.cameras, train.load_images()[0].numpy(), ctx.config["sfm"],
                                       seed=ctx.seed, log=ctx.log)
        if len(points["xyz"]) < MIN_POINTS:
            why = f"only {len(points['xyz'])} points triangulated from the {len(train)} posed training views"
            raise NotApplicable(why) if cfg["source"] == "auto" else RadfieldError(why)
    if source in ("points", "triangulate"):
        v, f, figures = build_envelope(points["xyz"], cfg)
    elif source == "mesh":
        mesh = points["mesh_vertices"]  # a mesh.ply without faces is a point cloud
        v, f, figures = build_envelope((mesh, points["mesh_faces"]) if len(points["mesh_faces"]) else mesh, cfg)
    else:
        _, masks = train.load_images()  # views without alpha count as all foreground
        v, f, figures = visual_hull(train.cameras, list(masks.numpy()), cfg)
    write_envelope(ctx.outputs[ENVELOPE], v, f)
    overlay_picture(v, f, train.cameras[0], train.load_image(0)[0].numpy(), ctx.outputs[OVERLAY])
    ctx.log(f"{figures['faces']} faces from the {source}, margin {figures['margin']:.3g}")
    return {"source": source, **figures}


STAGE = Stage("envelope", run, config_keys=("envelope", "sfm", "seed"), inputs=(SCENE, POINTS),
              outputs=(ENVELOPE, OVERLAY))


def check_config(config: dict[str, Any]) -> None:
    """The `envelope` settings a user can get wrong, checked before anything runs."""
    for key in ("offset", "wrap_alpha", "outlier_std"):
        require(config, f"envelope.{key}", lambda x: x > 0, "positive")
    require(config, "envelope.poisson_depth", lambda n: 1 <= n <= 16, "between 1 and 16")
    require(config, "envelope.target_faces", lambda n: n >= 20, "at least 20")
    require(config, "envelope.hull_resolution", lambda n: n >= 8, "at least 8")
    require(config, "envelope.num_threads", lambda n: n >= 1, "at least 1")


def choose_source(source: str, points: dict[str, np.ndarray], train: Dataset) -> str:
    """What the envelope is built from ("auto" resolved, see the module docstring); RadfieldError
    when the configured source is missing."""
    present = {"points": len(points["xyz"]) > 0, "mesh": len(points["mesh_vertices"]) > 0}
    if source in present:
        if not present[source]:
            what = "SfM points" if source == "points" else "mesh.ply"
            raise RadfieldError(f"config key envelope.source is {source} but the dataset has no {what}")
        return source
    if source == "auto" and any(present.values()):
        return next(name for name, there in present.items() if there)
    if source == "triangulate":
        return source
    masked = train.load_image(0)[1] is not None  # the first image tells: datasets are RGB or RGBA throughout
    if source == "hull" and not masked:
        raise RadfieldError(f"config key envelope.source is hull but the images of {train.root} have no alpha channel")
    return "hull" if masked else "triangulate"


def build_envelope(geometry, cfg: dict) -> tuple[np.ndarray, np.ndarray, dict]:
    """Envelope of a point cloud `geometry` (N, 3) or of a mesh given as a tuple `geometry` =
    (vertices (V, 3), faces (F, 3)), with the `envelope` section `cfg` of the config. Returns
    vertices (V', 3) float64, faces (F', 3) int64 (outward orientation) and the figures `faces`,
    `vertices`, `method` (reconstruction used), `points_outside` (inliers outside the envelope),
    `self_intersections`, `margin` (absolute) and, for points, `inliers`, `outliers` and `rejected`
    (why the reconstructions tried before `method` were not used)."""
    if cfg["method"] not in METHODS:
        raise RadfieldError(f"envelope: unknown method {cfg['method']!r} (one of {', '.join(METHODS)})")
    if isinstance(geometry, tuple):
        v, f = (np.asarray(a) for a in geometry)
        _check_array(v, "mesh vertices")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise RadfieldError(f"envelope: mesh faces must be a non-empty (F, 3) array, got shape {f.shape}")
        return _envelope_of((v, f), v, "mesh", _diagonal(v), cfg)

    points = np.asarray(geometry, dtype=np.float64)
    _check_array(points, "points")
    if len(points) < MIN_POINTS:
        raise RadfieldError(f"envelope: {len(points)} points, need at least {MIN_POINTS} to build a surface")
    inliers = _remove_outliers(points, cfg)
    diag = _diagonal(inliers)
    failures = []
    first = "poisson" if cfg["method"] == "auto" else cfg["method"]
    for name in dict.fromkeys((first, *FALLBACKS)):  # ordered, without duplicates
        surface = _surface(inliers, name, diag, cfg)
        if isinstance(surface, str):
            failures.append(f"{name}: {surface}")
            continue
        v, f, figures = _envelope_of(surface, inliers, name, diag, cfg)
        if figures["points_outside"] <= MAX_OUTSIDE_FRACTION * len(inliers):
            return v, f, {**figures, "inliers": len(inliers), "outliers": len(points) - len(inliers),
                          "rejected": "; ".join(failures)}
        failures.append(f"{name}: {figures['points_outside']} points outside")
    raise RadfieldError("envelope: no surface enclosed the points (" + "; ".join(failures) + ")")


def _envelope_of(surface, points: np.ndarray, name: str, diag: float, cfg: dict):
    """Wrap `surface` (vertices, faces) at the margin, decimate, check; count the `points` outside."""
    margin = cfg["offset"] * diag
    v, f = _wrap(*surface, alpha=cfg["wrap_alpha"] * diag, offset=margin)
    v, f, checks = _decimate_and_check(v, f, cfg["target_faces"])
    outside = int((signed_distance(points, v, f) > 0).sum())
    return v, f, {"method": name, "faces": len(f), "vertices": len(v), "points_outside": outside,
                  "self_intersections": checks["self_intersections"], "margin": margin}


def _remove_outliers(points: np.ndarray, cfg: dict) -> np.ndarray:
    """Two tests, because each misses what the other catches. Statistical (global): drop points
    whose mean distance to their k nearest neighbours exceeds the mean of that over all points by
    `outlier_std` standard deviations - this removes scattered floaters, which look like a
    sparse but normal region to a local test. Then LoOP (local outlier probability, pymeshlab):
    drop points much sparser than their own neighbourhood."""
    k = min(OUTLIER_NEIGHBORS, len(points) - 1)
    distance, _ = cKDTree(points).query(points, k=k + 1)
    spacing = distance[:, 1:].mean(1)
    points = points[spacing <= spacing.mean() + cfg["outlier_std"] * spacing.std()]
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=points))
    ms.compute_selection_point_cloud_outliers(propthreshold=OUTLIER_PROBABILITY, knearest=min(k, len(points) - 1))
    return points[~ms.current_mesh().vertex_selection_array()]


def _surface(points: np.ndarray, name: str, diag: float, cfg: dict):
    """A triangle surface through the points: (vertices, faces), or a string saying why not."""
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=points))
    try:
        if name == "poisson":
            ms.compute_normal_for_point_clouds(k=10, smoothiter=2)
            ms.generate_surface_reconstruction_screened_poisson(
                depth=cfg["poisson_depth"], threads=cfg["num_threads"]
            )
        elif name == "ball_pivoting":
            ms.generate_surface_reconstruction_ball_pivoting()
        elif name == "alpha":
            with _quiet_c_output():  # qhull prints its own report
                ms.generate_alpha_shape(alpha=pymeshlab.PureValue(ALPHA_SHAPE * diag), filtering="Alpha Shape")
        else:
            ms.generate_convex_hull()
    except pymeshlab.PyMeshLabException as exc:
        return f"failed ({exc})"
    mesh = ms.current_mesh()
    if mesh.face_number() == 0:
        return "no faces"
    if name in ("poisson", "ball_pivoting"):
        # The alpha wrap would close an open surface into a thin shell around it, with the inside
        # of the object outside the envelope: only closed reconstructions are used as they are.
        topology = ms.get_topological_measures()
        if topology["boundary_edges"] or not topology["is_mesh_two_manifold"]:
            return f"not watertight ({topology['boundary_edges']} boundary edges)"
        lo, hi = points.min(0), points.max(0)
        box = mesh.bounding_box()
        if max((lo - box.min()).max(), (box.max() - hi).max()) > MAX_BULGE * diag:
            return "bulges far beyond the points"
    return mesh.vertex_matrix(), mesh.face_matrix()


def _wrap(v, f, alpha: float, offset: float) -> tuple[np.ndarray, np.ndarray]:
    """CGAL alpha wrap (pymeshlab) of a triangle mesh: watertight, 2-manifold, no self-intersections,
    `offset` outside the input. (The filter crashes on a mesh without faces: callers pass triangles.)"""
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(v, np.float64), face_matrix=np.asarray(f, np.int32)))
    ms.generate_alpha_wrap(alpha=pymeshlab.PureValue(alpha), offset=pymeshlab.PureValue(offset))
    return ms.current_mesh().vertex_matrix(), ms.current_mesh().face_matrix()


def _decimate_and_check(v, f, target_faces: int):
    """Decimate to `target_faces` (fast-simplification), orient outward, check; a mesh that is not
    watertight afterwards is an error (a cage cannot be built inside it)."""
    if len(f) > target_faces:
        v, f = fast_simplification.simplify(v, f, target_count=int(target_faces))
    v, f = _outward(np.asarray(v, np.float64), np.asarray(f, np.int64))
    checks = mesh_checks(v, f)
    if not checks["watertight"]:
        raise RadfieldError(f"envelope: the decimated envelope is not watertight ({len(f)} faces)")
    return v, f, checks


def mesh_checks(vertices: np.ndarray, faces: np.ndarray) -> dict:
    """`watertight` (closed 2-manifold, one piece or several) and the number of
    `self_intersections` (faces that cross another face), from pymeshlab."""
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=vertices, face_matrix=faces.astype(np.int32)))
    topology = ms.get_topological_measures()
    ms.compute_selection_by_self_intersections_per_face()
    return {
        "watertight": topology["boundary_edges"] == 0 and topology["is_mesh_two_manifold"],
        "self_intersections": ms.current_mesh().selected_face_number(),
    }


def signed_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Signed distance (N,) from points to a closed, outward-oriented mesh: positive outside (VTK)."""
    surface = pv.PolyData.from_regular_faces(vertices, faces)
    return np.asarray(pv.PolyData(np.asarray(points, np.float64)).compute_implicit_distance(surface)["implicit_distance"])


def _outward(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flip the faces if the enclosed volume is negative (inward normals)."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    volume = np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0
    return (v, f) if volume > 0 else (v, f[:, ::-1].copy())


def visual_hull(cameras: list[Camera], masks: list[np.ndarray], cfg: dict):
    """Envelope carved from silhouettes, with the `envelope` section `cfg` of the config.
    `masks[k]` is (H, W) for `cameras[k]` (bool, or alpha in [0, 1]: foreground above
    MASK_THRESHOLD). A voxel is removed when some view sees it entirely on background, and kept
    only if it projects into at least HULL_MIN_VIEWS of the images.
    Carving is conservative: a voxel goes only when its whole bounding sphere projects onto
    background. The surface lies `offset` x diagonal (plus half a voxel) outside the kept voxels
    (distance transform + marching cubes), decimated to `target_faces`. Returns vertices, faces, figures
    (`faces`, `vertices`, `voxels`, `voxel_size`, `self_intersections`, `margin`)."""
    if len(cameras) != len(masks) or not cameras:
        raise RadfieldError(f"visual hull: {len(cameras)} cameras but {len(masks)} masks")
    views = []
    for cam, mask in zip(cameras, masks):
        mask = np.asarray(mask)
        if mask.shape != (cam.height, cam.width):
            raise RadfieldError(f"visual hull: mask of {cam.name!r} is {mask.shape}, camera is {cam.height}x{cam.width}")
        background = (mask <= MASK_THRESHOLD).astype(np.uint8)
        # distance (pixels) from each pixel to the nearest foreground pixel
        views.append((cam, cv2.distanceTransform(background, cv2.DIST_L2, 5)))

    box = _rig_box(cameras)
    # Silhouette cones from a ring of cameras also meet far outside the object, where only a few
    # views see; asking for many views bounds the hull to the region the capture covers.
    min_views = max(1, int(np.ceil(HULL_MIN_VIEWS * len(views))))
    for resolution in (32, int(cfg["hull_resolution"])):  # a coarse pass finds the object's box
        occupied, origin, h = _carve(views, *box, resolution, min_views)
        if not occupied.any():
            raise RadfieldError("visual hull: the silhouettes have no common volume (empty masks or wrong poses?)")
        idx = np.argwhere(occupied)
        box = origin + (idx.min(0) - 1) * h, origin + (idx.max(0) + 2) * h

    diag = float(np.linalg.norm((idx.max(0) - idx.min(0) + 1) * h))
    # the object lies within half a voxel diagonal of the kept voxel centres
    offset = cfg["offset"] * diag + h * np.sqrt(3) / 2
    pad = int(np.ceil(offset / h)) + 2
    grid = np.pad(occupied, pad)
    distance = ndimage.distance_transform_edt(~grid, sampling=h)
    verts, faces, _, _ = marching_cubes(distance, level=offset, spacing=(h, h, h))
    verts = verts + origin + (0.5 - pad) * h  # grid index k is the voxel centre origin + (k + 0.5) h
    v, f, checks = _decimate_and_check(verts, faces, cfg["target_faces"])
    return v, f, {"faces": len(f), "vertices": len(v), "voxels": int(occupied.sum()), "voxel_size": h,
                  "self_intersections": checks["self_intersections"], "margin": float(offset)}


def _rig_box(cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """A cube that holds what the cameras look at: centred on the point nearest to all optical axes
    (least squares), half-size the largest camera distance from it."""
    centers = np.array([c.c2w[:3, 3].numpy() for c in cameras])
    axes = np.array([c.c2w[:3, 2].numpy() for c in cameras])
    projectors = np.eye(3) - axes[:, :, None] * axes[:, None, :]  # onto the plane normal to each axis
    target, *_ = np.linalg.lstsq(projectors.sum(0), np.einsum("nij,nj->i", projectors, centers), rcond=None)
    radius = np.linalg.norm(centers - target, axis=1).max()
    return target - radius, target + radius


def _carve(views, lo: np.ndarray, hi: np.ndarray, resolution: int, min_views: int):
    """Occupancy (X, Y, Z) bool of the voxels of the box [lo, hi] (`resolution` voxels along its
    longest side) that are in at least `min_views` images and on no view's background; returns it
    with the grid origin and voxel size."""
    h = float((hi - lo).max()) / resolution
    shape = np.maximum(np.ceil((hi - lo) / h).astype(int), 1)
    axes = [lo[k] + (np.arange(shape[k]) + 0.5) * h for k in range(3)]
    centers = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    keep = np.ones(len(centers), bool)
    seen = np.zeros(len(centers), np.int64)
    radius = h * np.sqrt(3) / 2
    for cam, to_foreground in views:
        w2c = cam.w2c.numpy()
        p = centers @ w2c[:3, :3].T + w2c[:3, 3]
        z = p[:, 2]
        front = z > radius  # voxels around or behind the camera are not judged by it
        zs = np.where(front, z, 1.0)
        u, v = cam.fx * p[:, 0] / zs + cam.cx, cam.fy * p[:, 1] / zs + cam.cy
        inside = front & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        j = np.clip(u.astype(int), 0, cam.width - 1)
        i = np.clip(v.astype(int), 0, cam.height - 1)
        # projected bounding-sphere radius in pixels (+1 pixel for the pixel-centre lookup)
        r_pix = max(cam.fx, cam.fy) * radius / np.sqrt(np.maximum(zs**2 - radius**2, 1e-12)) + 1.0
        keep &= ~(inside & (to_foreground[i, j] > r_pix))
        seen += inside
    return (keep & (seen >= min_views)).reshape(shape), lo, h


def overlay_picture(vertices: np.ndarray, faces: np.ndarray, camera: Camera, image: np.ndarray, path=None) -> np.ndarray:
    """The envelope drawn over one view: tinted silhouette, the edges of the faces turned towards
    the camera, and the outline. `image` is (H, W, 3) RGB, uint8 or float in [0, 1], the size of
    `camera`. Returns (H, W, 3) uint8 RGB and, if `path` is given, also writes it there as a PNG
    (atomically)."""
    if image.shape[:2] != (camera.height, camera.width):
        raise RadfieldError(f"overlay: image is {image.shape[1]}x{image.shape[0]}, "
                            f"camera {camera.name!r} is {camera.width}x{camera.height}")
    rgb = image[..., :3]
    rgb = (np.clip(rgb, 0, 1) * 255).round().astype(np.uint8) if rgb.dtype != np.uint8 else rgb.copy()
    w2c = camera.w2c.numpy()
    p = np.asarray(vertices, np.float64) @ w2c[:3, :3].T + w2c[:3, 3]  # camera space
    z = np.where(p[:, 2] > 1e-6, p[:, 2], np.nan)
    # pixel centres sit at (j + 0.5, i + 0.5); OpenCV draws at integer coordinates, 4 fraction bits
    uv = np.stack([camera.fx * p[:, 0] / z + camera.cx - 0.5, camera.fy * p[:, 1] / z + camera.cy - 0.5], -1)
    visible = np.isfinite(uv[faces]).all((1, 2))  # faces with a corner behind the camera are left out
    faces = faces[visible]
    tris = np.round(uv[faces] * 16).astype(np.int32)
    normals = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    facing = np.einsum("ij,ij->i", normals, p[faces[:, 0]]) < 0  # outward normal towards the camera
    silhouette = np.zeros(rgb.shape[:2], np.uint8)
    for tri in tris:  # one by one: fillPoly would apply the even-odd rule to overlapping triangles
        cv2.fillConvexPoly(silhouette, tri, 255, lineType=cv2.LINE_AA, shift=4)
    alpha = (silhouette.astype(np.float32) / 255 * 0.3)[..., None]
    out = (rgb * (1 - alpha) + np.array([255, 160, 0], np.float32) * alpha).astype(np.uint8)  # orange tint
    wire = out.copy()
    cv2.polylines(wire, list(tris[facing]), True, (255, 230, 150), 1, lineType=cv2.LINE_AA, shift=4)
    out = cv2.addWeighted(out, 0.4, wire, 0.6, 0.0)
    contours, _ = cv2.findContours((silhouette > 127).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(out, contours, -1, (255, 80, 0), 2, lineType=cv2.LINE_AA)
    if path is not None:
        atomic_write(Path(path), lambda tmp: _imwrite(tmp, out))
    return out


def write_envelope(path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write the envelope as a binary PLY (float32 vertices), atomically."""
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(vertices, np.float64), face_matrix=np.asarray(faces, np.int32)))
    atomic_write(Path(path), lambda tmp: ms.save_current_mesh(str(tmp), binary=True, save_vertex_color=False,
                                                              save_vertex_normal=False, save_face_color=False))


def read_envelope(path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 and faces (F, 3) int64 of a triangle mesh file (PLY, OBJ, ...)."""
    ms = pymeshlab.MeshSet()
    try:
        ms.load_new_mesh(str(path))
    except pymeshlab.PyMeshLabException as exc:
        raise RadfieldError(f"{path}: not a readable mesh ({exc})") from None
    mesh = ms.current_mesh()
    return mesh.vertex_matrix().copy(), mesh.face_matrix().astype(np.int64)


def _imwrite(path: Path, rgb: np.ndarray) -> None:
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise RadfieldError(f"{path}: could not write the image")


def _diagonal(points: np.ndarray) -> float:
    diag = float(np.linalg.norm(points.max(0) - points.min(0)))
    if diag <= 0:
        raise RadfieldError("envelope: all points coincide")
    return diag


def _check_array(a: np.ndarray, what: str) -> None:
    if a.ndim != 2 or a.shape[1] != 3 or len(a) == 0 or not np.isfinite(a).all():
        raise RadfieldError(f"envelope: {what} must be a non-empty finite (N, 3) array, got shape {a.shape}")


@contextlib.contextmanager
def _quiet_c_output():
    """Silence C-level stdout and stderr (qhull inside pymeshlab prints its report to them)."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        yield
    finally:
        ctypes.CDLL(None).fflush(None)  # flush C stdio buffers into /dev/null, not later elsewhere
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)
