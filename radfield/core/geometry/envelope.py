"""The coarse envelope: a closed, outward-offset, decimated triangle mesh that encloses the object,
inside which the cage is built and the initial primitives are sampled.

From points (SfM) or a given mesh: `build_envelope`. From posed silhouettes: `visual_hull`; for a
dynamic scene (views of several moments) the union of the moments' hulls (`visual_hull(...,
groups=)`: carving with views of different moments would remove what moves).
Every branch ends in the same finish and the same fallbacks, so a valid input always gives an
envelope:

1. the branch's surface (screened Poisson / ball pivoting / alpha shape through the points, the
   given mesh, or the marching-cubes surface of the carved voxels) is wrapped with CGAL alpha
   wrapping at the margin (pymeshlab `generate_alpha_wrap`: watertight, 2-manifold, no
   self-intersections, `margin` outside its input, several parts and holes kept apart), then
   decimated to the target face count so that it stays closed and holds its points:
   fast-simplification, else quadric edge collapse with topology preserved, else no decimation
   but coarser wraps (alpha doubled until the face budget is met: a wrap is closed by construction);
2. for points, the alpha shape and the convex hull are tried the same way when the surface is open
   or leaves points outside;
3. the fallbacks that cannot fail: the convex hull of the points grown by the margin (scipy/qhull,
   no wrap, no decimation), then the box of the points' bounds grown by the margin.

The figures record which surface was used (`method`), whether a fallback was taken (`fallback`:
None, or the surface that replaced the branch's first choice) and why (`fallback_reason`).
`overlay_picture` draws an envelope over one input view so a user can check it.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy import ndimage
# pymeshlab, pyvista, fast_simplification, cv2 and scikit-image are imported in the functions that use
# them: a run without an envelope (--no-cage) must work on a machine that lacks them
from scipy.spatial import ConvexHull, QhullError, cKDTree

from radfield.util.atomic import atomic_write
from radfield.core.geometry.cameras import Camera
from radfield.errors import RadfieldError

SOURCES = ("auto", "points", "mesh", "hull", "triangulate", "none")
METHODS = ("auto", "poisson", "ball_pivoting", "alpha", "convex")
# Fallback surfaces through points after the configured one. Alpha shape and convex hull cannot
# fail to cover the points; the convex hull comes last because it fills every concavity.
POINT_FALLBACKS = ("alpha", "convex")
# The fallbacks at the end of every branch, in order (they cannot fail; see the module docstring).
LAST_RESORTS = ("convex_hull", "box")

# Algorithm constants (the tunable settings are the `envelope` section of pipeline.yaml).
MIN_POINTS = 10  # fewer points make no surface
CARVING_PASSES = 3  # the visual hull carves a coarse grid, then its fine grid twice (visual_hull)
OUTLIER_NEIGHBORS = 16  # k of both outlier tests
OUTLIER_PROBABILITY = 0.8  # LoOP test: points more likely than this to be outliers are dropped
ALPHA_SHAPE = 0.1  # alpha-shape fallback radius, fraction of the bounding-box diagonal
MAX_OUTSIDE_FRACTION = 0.005  # points allowed outside before trying the next surface
# A reconstruction whose box sticks out of the points' box by more than this fraction of the
# diagonal has bulged (screened Poisson closes open scans with large bubbles).
MAX_BULGE = 0.1
COARSER_WRAPS = 6  # alpha doublings tried when no decimation keeps the wrap closed
HULL_MIN_VIEWS = 0.5  # visual hull: fraction of the views a voxel must project into
MASK_THRESHOLD = 0.5  # visual hull: alpha above this is foreground
RIG_BOX = 0.5  # no common silhouette volume: box of this fraction of the mean camera distance
# Vertices of an icosahedron of circumradius 1; its inradius is 0.7947: scaled by 1/0.7947 it holds
# the unit ball, so a point set plus these offsets has a convex hull that holds the point set's
# margin-neighbourhood.
_ICOSAHEDRON = np.array([(0, s1, s2 * 1.618034) for s1 in (-1, 1) for s2 in (-1, 1)]
                        + [(s1, s2 * 1.618034, 0) for s1 in (-1, 1) for s2 in (-1, 1)]
                        + [(s2 * 1.618034, 0, s1) for s1 in (-1, 1) for s2 in (-1, 1)], float) / 1.9021130
_ICOSAHEDRON_INRADIUS = 0.7946545


def choose_source(source: str, has_points: bool, has_mesh: bool, masked: bool) -> str:
    """What the envelope is built from, `auto` resolved to the first of points, mesh, hull (the
    images have alpha), triangulate; RadfieldError when the configured source is missing."""
    present = {"points": has_points, "mesh": has_mesh}
    if source in present:
        if not present[source]:
            what = "SfM points" if source == "points" else "mesh.ply"
            raise RadfieldError(f"config key envelope.source is {source} but the dataset has no {what}")
        return source
    if source == "auto" and any(present.values()):
        return next(name for name, there in present.items() if there)
    if source in ("triangulate", "none"):
        return source
    if source == "hull" and not masked:
        raise RadfieldError("config key envelope.source is hull but the training images have no alpha channel")
    return "hull" if masked else "triangulate"


# --- the branches ---------------------------------------------------------------------------------


def build_envelope(geometry, cfg: dict) -> tuple[np.ndarray, np.ndarray, dict]:
    """Envelope of a point cloud `geometry` (N, 3) or of a mesh given as a tuple `geometry` =
    (vertices (V, 3), faces (F, 3)), with the `envelope` section `cfg` of the config. Returns
    vertices (V', 3) float64, faces (F', 3) int64 (outward orientation) and the figures `faces`,
    `vertices`, `method` (surface used), `decimation`, `points_outside` (points outside the
    envelope), `self_intersections`, `margin` (absolute), `fallback`, `fallback_reason` and, for
    points, `inliers` and `outliers`."""
    if cfg["method"] not in METHODS:
        raise RadfieldError(f"envelope: unknown method {cfg['method']!r} (one of {', '.join(METHODS)})")
    if isinstance(geometry, tuple):
        v, f = (np.asarray(a) for a in geometry)
        _check_array(v, "mesh vertices")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise RadfieldError(f"envelope: mesh faces must be a non-empty (F, 3) array, got shape {f.shape}")
        v = v.astype(np.float64)
        return finish([("mesh", lambda: (v, f))], v, _diagonal(v), cfg)

    points = np.asarray(geometry, dtype=np.float64)
    _check_array(points, "points")
    if len(points) < MIN_POINTS:
        raise RadfieldError(f"envelope: {len(points)} points, need at least {MIN_POINTS} to build a surface")
    inliers = _remove_outliers(points, cfg)
    if len(inliers) < MIN_POINTS:
        inliers = points  # outlier tests on a tiny or degenerate set: keep every point
    diag = _diagonal(inliers)
    first = "poisson" if cfg["method"] == "auto" else cfg["method"]
    surfaces = [(name, lambda name=name: _surface(inliers, name, diag, cfg))
                for name in dict.fromkeys((first, *POINT_FALLBACKS))]  # ordered, without duplicates
    v, f, figures = finish(surfaces, inliers, diag, cfg)
    return v, f, {**figures, "inliers": len(inliers), "outliers": len(points) - len(inliers)}


def visual_hull(cameras: list[Camera], masks: list[np.ndarray], cfg: dict, groups: list[list[int]] | None = None,
                on_carved: Callable[[], None] | None = None):
    """Envelope carved from silhouettes, with the `envelope` section `cfg` of the config.
    `masks[k]` is (H, W) for `cameras[k]` (bool, or alpha in [0, 1]: foreground above
    MASK_THRESHOLD). A voxel is removed when some view sees it entirely on background, and kept
    only if it projects into at least HULL_MIN_VIEWS of the images (every voxel seen by one view
    counts when that leaves none). A voxel beyond an image's border is not carved by that view,
    and counts as seen by it when the silhouette touches the border nearest to it (an object cut
    off by the frame). Carving is conservative: a voxel goes only when its whole bounding
    sphere projects onto background, so the object lies within half a voxel diagonal of the kept
    voxel centres; the marching-cubes surface at that distance goes through `finish`, which must
    hold every kept voxel centre. Returns vertices, faces and the figures of `build_envelope`
    plus `voxels` and `voxel_size`; silhouettes with no common volume give the box fallback.
    `groups`: lists of indices into `cameras`, each carved on its own (the views of one moment
    of a dynamic scene, each voxel judged by its group's views only) on one shared grid; the
    hull is the union of the groups' hulls, so it holds the object at every moment. None: one
    group of every view. on_carved() is called after each group's carving of each of the
    CARVING_PASSES passes (a progress bar's advance; a second round of passes follows when the
    strict one keeps nothing)."""
    import cv2
    from skimage.measure import marching_cubes

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

    view_groups = [[views[k] for k in group] for group in (groups or [range(len(views))])]
    rig_lo, rig_hi = _rig_box(cameras)
    # Silhouette cones from a ring of cameras also meet far outside the object, where only a few
    # views see; asking for many views bounds the hull to the region the capture covers.
    strict = tuple(max(1, int(np.ceil(HULL_MIN_VIEWS * len(group)))) for group in view_groups)
    for min_views in dict.fromkeys((strict, (1,) * len(view_groups))):
        box = rig_lo, rig_hi
        # a coarse pass finds the object's box, a fine one carves it, and a second fine pass in
        # the fine pass's box (large coarse voxels survive farther out) spends the resolution on it
        for resolution in (32, int(cfg["hull_resolution"]), int(cfg["hull_resolution"])):   # CARVING_PASSES of them
            occupied, origin, h = _carve_union(view_groups, *box, resolution, min_views, on_carved)
            if not occupied.any():
                break
            idx = np.argwhere(occupied)
            box = origin + (idx.min(0) - 1) * h, origin + (idx.max(0) + 2) * h
        if occupied.any():
            break
    else:
        return focus_box(cameras, "the silhouettes have no common volume (empty masks or wrong poses?)")

    centres = origin + (idx + 0.5) * h
    diag = float(np.linalg.norm((idx.max(0) - idx.min(0) + 1) * h))
    reach = h * np.sqrt(3) / 2  # the object lies within half a voxel diagonal of the kept centres
    pad = 3
    distance = ndimage.distance_transform_edt(~np.pad(occupied, pad), sampling=h)
    verts, faces, _, _ = marching_cubes(distance, level=reach, spacing=(h, h, h))
    verts = verts + origin + (0.5 - pad) * h  # grid index k is the voxel centre origin + (k + 0.5) h
    v, f, figures = finish([("hull", lambda: (verts, faces))], centres, diag, cfg, extra_margin=reach)
    return v, f, {**figures, "voxels": int(occupied.sum()), "voxel_size": h}


def focus_box(cameras: list[Camera], reason: str):
    """The box fallback of `visual_hull`: a cube about the point the cameras look at (nearest to
    all optical axes), half-size RIG_BOX × the mean camera distance from it; also the envelope of a
    dynamic scene whose moments have too few views each for their own hulls (D-NeRF's monocular
    captures: one view a moment). Vertices, faces and `visual_hull`'s figures, `reason` the fallback's."""
    rig_lo, rig_hi = _rig_box(cameras)
    centre = (rig_lo + rig_hi) / 2
    half = RIG_BOX * np.mean([np.linalg.norm(c.center.numpy() - centre) for c in cameras])
    v, f = box_envelope(centre - half, centre + half, 0.0)
    return v, f, {**_figures(v, f, "box", "none", 0, 0.0, "box", reason), "voxels": 0, "voxel_size": None}


# --- the common finish ----------------------------------------------------------------------------


def finish(surfaces: list[tuple[str, Callable]], points: np.ndarray, diag: float, cfg: dict,
           extra_margin: float = 0.0) -> tuple[np.ndarray, np.ndarray, dict]:
    """The first of `surfaces` (name, function returning (vertices, faces) or a string saying why
    not) that wraps and decimates into a closed envelope holding all but MAX_OUTSIDE_FRACTION of
    `points`, else the last resorts; see the module docstring. The margin is `offset` x `diag` (+
    `extra_margin`, which the surface already lies outside `points` by)."""
    import pymeshlab

    margin = cfg["offset"] * diag
    failures = []
    for name, make in surfaces:
        try:
            result = make()
            if not isinstance(result, str):
                result = _wrap_and_decimate(result, points, cfg["wrap_alpha"] * diag, margin, cfg["target_faces"])
        except pymeshlab.PyMeshLabException as exc:  # the filters raise on inputs they cannot handle
            result = f"failed ({exc})"
        if isinstance(result, str):
            failures.append(f"{name}: {result}")
            continue
        v, f, decimation, outside = result
        fallback = None if name == surfaces[0][0] else name
        return v, f, _figures(v, f, name, decimation, outside, margin + extra_margin, fallback, "; ".join(failures))
    return last_resort(points, margin + extra_margin, "; ".join(failures))


def last_resort(points: np.ndarray, margin: float, reason: str) -> tuple[np.ndarray, np.ndarray, dict]:
    """The convex hull of `points` grown by `margin`, or when qhull cannot build one (fewer than 4
    points, all on a plane) the box of their bounds grown by `margin`: closed meshes that hold
    every point. `reason` says why the branch's surfaces were not used."""
    points = np.asarray(points, np.float64)
    try:
        v, f = convex_envelope(points, margin)
        name = "convex_hull"
    except (QhullError, ValueError) as exc:
        reason = f"{reason}; convex hull: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
        v, f = box_envelope(points.min(0), points.max(0), margin)
        name = "box"
    outside = int((signed_distance(points, v, f) > 0).sum())
    return v, f, _figures(v, f, name, "none", outside, margin, name, reason)


def convex_envelope(points: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Convex hull (vertices, outward faces) of `points` grown so it holds every point's
    `margin`-ball: the hull of the hull vertices offset along an icosahedron that holds the ball."""
    points = np.asarray(points, np.float64)
    corners = points[ConvexHull(points).vertices] if len(points) > 4 else points
    grown = (corners[:, None] + _ICOSAHEDRON * (margin / _ICOSAHEDRON_INRADIUS)).reshape(-1, 3)
    hull = ConvexHull(grown)
    v, f = _compact(hull.points, hull.simplices.astype(np.int64))
    faces = f.copy()
    normal = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    flip = np.einsum("ij,ij->i", normal, hull.equations[:, :3]) < 0  # qhull's outward normals
    faces[flip] = f[flip][:, ::-1]
    return v, faces


def box_envelope(lo: np.ndarray, hi: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The box [lo - margin, hi + margin] (at least a thousandth of its size, or of 1, on every
    side, so even one point gets a box) as 8 vertices and 12 outward triangles."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    grow = np.maximum(margin, 1e-3 * max(float((hi - lo).max()), float(np.abs(np.r_[lo, hi]).max()), 1.0))
    lo, hi = lo - grow, hi + grow
    v = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int64)
    return _outward(v, f)


def _figures(v, f, method, decimation, outside, margin, fallback, reason) -> dict:
    return {"method": method, "faces": len(f), "vertices": len(v), "decimation": decimation,
            "points_outside": int(outside), "self_intersections": mesh_checks(v, f)["self_intersections"],
            "margin": float(margin), "fallback": fallback, "fallback_reason": " ".join(reason.split()) or None}


def _wrap_and_decimate(surface, points: np.ndarray, alpha: float, margin: float, target_faces: int):
    """(vertices, faces, how it was decimated, points outside) of the wrapped, decimated surface,
    or a string saying why no decimation kept it closed and holding the points."""
    v, f = surface
    if len(f) == 0:
        return "no faces"
    wrapped = _wrap(v, f, alpha, margin)
    allowed = MAX_OUTSIDE_FRACTION * len(points)
    if len(wrapped[1]) <= target_faces:
        result = _accepted(wrapped, points, allowed)
        return result if isinstance(result, str) else (result[0], result[1], "none", result[2])
    tried = []
    for name, decimate in (("fast_simplification", _fast_simplification), ("quadric_topology", _quadric)):
        result = _accepted(decimate(*wrapped, target_faces), points, allowed)
        if not isinstance(result, str):
            return result[0], result[1], name, result[2]
        tried.append(f"{name}: {result}")
    # No decimation kept it closed: a coarser wrap is closed by construction and needs none.
    for doubling in range(1, COARSER_WRAPS + 1):
        coarse = _wrap(v, f, alpha * 2**doubling, margin)
        if len(coarse[1]) <= target_faces or doubling == COARSER_WRAPS:
            result = _accepted(coarse, points, allowed)
            if not isinstance(result, str):
                return result[0], result[1], f"coarse_wrap_x{2**doubling}", result[2]
            tried.append(f"coarse wrap: {result}")
            break
    return "; ".join(tried)


def _accepted(mesh, points: np.ndarray, allowed: float):
    """(vertices, faces, points outside) of an outward-oriented `mesh` that is closed and holds
    all but `allowed` of the points, or a string saying what is wrong."""
    v, f = _outward(np.asarray(mesh[0], np.float64), np.asarray(mesh[1], np.int64))
    if len(f) < 4 or not mesh_checks(v, f)["watertight"]:
        return f"not watertight after decimation ({len(f)} faces)"
    outside = int((signed_distance(points, v, f) > 0).sum())
    if outside > allowed:
        return f"{outside} points outside"
    return v, f, outside


def _fast_simplification(v, f, target_faces: int):
    import fast_simplification

    return fast_simplification.simplify(v, f, target_count=int(target_faces))


def _quadric(v, f, target_faces: int):
    """Quadric edge collapse that refuses collapses changing the topology (pymeshlab)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(v, np.float64), face_matrix=np.asarray(f, np.int32)))
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(target_faces), preservetopology=True,
                                                preservenormal=True, planarquadric=True)
    return ms.current_mesh().vertex_matrix(), ms.current_mesh().face_matrix()


def _remove_outliers(points: np.ndarray, cfg: dict) -> np.ndarray:
    """Two tests, because each misses what the other catches. Statistical (global): drop points
    whose mean distance to their k nearest neighbours exceeds the mean of that over all points by
    `outlier_std` standard deviations - this removes scattered floaters, which look like a
    sparse but normal region to a local test. Then LoOP (local outlier probability, pymeshlab):
    drop points much sparser than their own neighbourhood."""
    import pymeshlab

    k = min(OUTLIER_NEIGHBORS, len(points) - 1)
    distance, _ = cKDTree(points).query(points, k=k + 1)
    spacing = distance[:, 1:].mean(1)
    points = points[spacing <= spacing.mean() + cfg["outlier_std"] * spacing.std()]
    if len(points) <= k:
        return points
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=points))
    ms.compute_selection_point_cloud_outliers(propthreshold=OUTLIER_PROBABILITY, knearest=min(k, len(points) - 1))
    return points[~ms.current_mesh().vertex_selection_array()]


def _surface(points: np.ndarray, name: str, diag: float, cfg: dict):
    """A triangle surface through the points: (vertices, faces), or a string saying why not."""
    import pymeshlab

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
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(v, np.float64), face_matrix=np.asarray(f, np.int32)))
    ms.generate_alpha_wrap(alpha=pymeshlab.PureValue(alpha), offset=pymeshlab.PureValue(offset))
    return ms.current_mesh().vertex_matrix(), ms.current_mesh().face_matrix()


# --- checks and queries ---------------------------------------------------------------------------


def mesh_checks(vertices: np.ndarray, faces: np.ndarray) -> dict:
    """`watertight` (closed 2-manifold, one piece or several) and the number of
    `self_intersections` (faces that cross another face), from pymeshlab."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(vertices, np.float64), face_matrix=np.asarray(faces, np.int32)))
    topology = ms.get_topological_measures()
    ms.compute_selection_by_self_intersections_per_face()
    return {
        "watertight": topology["boundary_edges"] == 0 and topology["is_mesh_two_manifold"],
        "self_intersections": ms.current_mesh().selected_face_number(),
    }


def signed_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Signed distance (N,) from points to a closed, outward-oriented mesh: positive outside (VTK)."""
    import pyvista as pv

    surface = pv.PolyData.from_regular_faces(np.asarray(vertices, np.float64), np.asarray(faces, np.int64))
    return np.asarray(pv.PolyData(np.asarray(points, np.float64)).compute_implicit_distance(surface)["implicit_distance"])


def sample_in_envelope(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """`n` points uniform in the volume a closed envelope holds (n, 3): uniform in its bounding box,
    kept when inside (signed distance < 0), in rounds until there are `n`. Deterministic given
    `rng`, and independent of any tetrahedralisation of the envelope."""
    lo, hi = np.min(vertices, 0), np.max(vertices, 0)
    kept: list[np.ndarray] = []
    total, batch = 0, max(64, 2 * n)
    for _ in range(64):
        if total >= n:
            break
        candidates = lo + (hi - lo) * rng.random((batch, 3))
        inside = candidates[signed_distance(candidates, vertices, faces) < 0]
        kept.append(inside)
        total += len(inside)
        batch = int(min(4 * batch, max(64, 2 * (n - total) * batch / max(len(inside), 1))))
    points = np.concatenate(kept) if kept else np.zeros((0, 3))
    if len(points) < n:
        raise RadfieldError(f"envelope: found {len(points)} of {n} points inside it (is it closed?)")
    return points[:n]


def inside_envelope(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Boolean (N,): which points lie inside the closed envelope."""
    if len(points) == 0:
        return np.zeros(0, bool)
    return signed_distance(points, vertices, faces) < 0


# --- files and pictures ---------------------------------------------------------------------------


def write_envelope(path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write the envelope as a binary PLY (float32 vertices), atomically."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(vertices, np.float64), face_matrix=np.asarray(faces, np.int32)))
    atomic_write(Path(path), lambda tmp: ms.save_current_mesh(str(tmp), binary=True, save_vertex_color=False,
                                                              save_vertex_normal=False, save_face_color=False))


def read_envelope(path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 and faces (F, 3) int64 of a triangle mesh file (PLY, OBJ, ...)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    try:
        ms.load_new_mesh(str(path))
    except pymeshlab.PyMeshLabException as exc:
        raise RadfieldError(f"{path}: not a readable mesh ({exc})") from None
    mesh = ms.current_mesh()
    return mesh.vertex_matrix().copy(), mesh.face_matrix().astype(np.int64)


def overlay_picture(vertices: np.ndarray, faces: np.ndarray, camera: Camera, image: np.ndarray, path=None) -> np.ndarray:
    """The envelope drawn over one view: tinted silhouette, the edges of the faces turned towards
    the camera, and the outline. `image` is (H, W, 3) RGB, uint8 or float in [0, 1], the size of
    `camera`. Returns (H, W, 3) uint8 RGB and, if `path` is given, also writes it there as a PNG
    (atomically)."""
    import cv2

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
    # faces with a corner behind the camera, or absurdly far off screen, are left out
    visible = np.isfinite(uv[faces]).all((1, 2)) & (np.abs(uv[faces]) < 1e5).all((1, 2))
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


# --- small helpers --------------------------------------------------------------------------------


def _rig_box(cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """A cube that holds what the cameras look at: centred on the point nearest to all optical axes
    (least squares), half-size the largest camera distance from it."""
    centers = np.array([c.c2w[:3, 3].numpy() for c in cameras])
    axes = np.array([c.c2w[:3, 2].numpy() for c in cameras])
    projectors = np.eye(3) - axes[:, :, None] * axes[:, None, :]  # onto the plane normal to each axis
    target, *_ = np.linalg.lstsq(projectors.sum(0), np.einsum("nij,nj->i", projectors, centers), rcond=None)
    radius = max(float(np.linalg.norm(centers - target, axis=1).max()), 1e-6)
    return target - radius, target + radius


def _carve_union(view_groups, lo: np.ndarray, hi: np.ndarray, resolution: int, min_views: tuple[int, ...],
                 on_carved: Callable[[], None] | None = None):
    """`_carve` of each group of views (with its own min_views) on the same grid, united;
    on_carved() after each group."""
    occupied = None
    for views, least in zip(view_groups, min_views):
        carved, origin, h = _carve(views, lo, hi, resolution, least)
        occupied = carved if occupied is None else occupied | carved
        if on_carved is not None:
            on_carved()
    return occupied, origin, h


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
        on_background = to_foreground[i, j] > r_pix  # at the pixel, or the border pixel nearest to it
        keep &= ~(inside & on_background)
        # a voxel beyond the border where the silhouette reaches it may be object cut off by the
        # frame: the view counts as seeing it, else objects filling the views lose their rims
        seen += inside | (front & ~on_background)
    return (keep & (seen >= min_views)).reshape(shape), lo, h


def _outward(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flip the faces if the enclosed volume is negative (inward normals)."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    volume = np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0
    return (v, f) if volume > 0 else (v, f[:, ::-1].copy())


def _compact(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop vertices no face uses, renumbering the faces."""
    used, inverse = np.unique(f, return_inverse=True)
    return v[used], inverse.reshape(f.shape)


def _imwrite(path: Path, rgb: np.ndarray) -> None:
    import cv2

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
