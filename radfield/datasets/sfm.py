"""Structure from motion: a folder of photos -> undistorted pinhole cameras, a sparse
point cloud and the scene normalisation, with pycolmap (COLMAP 4.x API).

The sfm stage (stages/sfm.py) calls `run_sfm` on a folder of photos: it writes RUN/sfm/colmap/, a
COLMAP dataset that the data stage then reads like any other.

Output folder (written to a temporary sibling, renamed into place at the end, so a killed or failed
run never leaves a half-written folder):

    images/              undistorted images (PINHOLE, same names as the inputs)
    sparse/              COLMAP binary model (cameras.bin, images.bin, points3D.bin, rigs.bin,
                         frames.bin) of those images, in NORMALISED world coordinates
                         (world-to-camera poses in OpenCV axes; the colmap format,
                         datasets/formats/colmap.py, reads the folder as a dataset)
    points.ply           sparse points (x, y, z float; red, green, blue uchar), normalised coordinates
    normalization.json   {"center": [3], "scale": s}: x_normalised = scale * (x_sfm - center); every
                         later artifact of the run (envelope, cage, models) is in the normalised
                         frame, so this file maps them back to COLMAP's own frame
    sfm.json             what happened: registered / unregistered images, matcher, timings

`triangulate` serves posed datasets without points (the triangulate stage, whose points init and
the envelope start from): the same features and matching, triangulated with the dataset's own
cameras held fixed.

Matching is exhaustive up to `exhaustive_max_images` images and sequential (neighbours in file-name
order) above. COLMAP's vocabulary-tree matching and sequential loop detection need a vocabulary
file that COLMAP downloads on first use; this tool runs offline, so neither is used.

pycolmap and OpenImageIO are imported inside the functions that use them: importing this module
(the sfm and envelope stages do) must work on a machine without pycolmap as long as no SfM runs.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from radfield.core.geometry.cameras import Camera
from radfield.errors import RadfieldError
from radfield.datasets.images import list_images, write_image
from radfield import run as layout

if TYPE_CHECKING:
    import pycolmap

FIGURES = ("registered_images", "total_images", "points", "reprojection_error")
NORMALIZATION_FILE = layout.NORMALIZATION_FILE  # in the output folder: how its frame relates to COLMAP's


def run_sfm(image_dir, out_dir, cfg: dict[str, Any], seed: int = 0,
            log: Callable[[str], None] = lambda _line: None) -> dict[str, Any]:
    """Reconstruct cameras and sparse points from the photos in `image_dir` (not recursive) into
    `out_dir` (layout in the module docstring) with the `sfm` section `cfg` of the config. Returns
    the figures `registered_images`, `total_images`, `points`, `reprojection_error` (mean, pixels).
    Raises RadfieldError."""
    image_dir, out_dir = Path(image_dir), Path(out_dir)
    names = _list_images(image_dir)
    sizes = _image_sizes(image_dir, names)

    out_dir.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    try:
        with _colmap_errors_only():
            report = _reconstruct(image_dir, names, len(set(sizes.values())) == 1, work, cfg, seed, log)
        _replace_dir(work / "result", out_dir)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return {k: report[k] for k in FIGURES}


def _reconstruct(image_dir: Path, names: list[str], one_size: bool, work: Path, cfg: dict, seed: int,
                 log: Callable[[str], None]) -> dict:
    """The COLMAP steps, all inside `work`; the finished output ends up in `work/result`."""
    import pycolmap

    pycolmap.set_random_seed(seed)
    database = work / "database.db"
    timings = {}

    log(f"extracting features from {len(names)} photos")
    t = time.perf_counter()
    # One shared camera when every photo has the same size (one camera, one zoom): many more
    # observations constrain the intrinsics.
    _extract(database, image_dir, names, pycolmap.CameraMode.SINGLE if one_size else pycolmap.CameraMode.PER_IMAGE,
             cfg["camera_model"], cfg)
    timings["extract"] = time.perf_counter() - t

    t = time.perf_counter()
    matcher = _match(database, len(names), cfg, log)
    timings["match"] = time.perf_counter() - t

    log("incremental mapping")
    t = time.perf_counter()
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = int(cfg["num_threads"])
    mapping.random_seed = int(seed)
    models = pycolmap.incremental_mapping(database, image_dir, work / "models", options=mapping)
    timings["map"] = time.perf_counter() - t
    if not models:
        raise RadfieldError(
            f"{image_dir}: no 3D model could be built from {len(names)} images - "
            "they do not overlap enough (too few matching features between photos)"
        )
    best_id, best = max(models.items(), key=lambda kv: kv[1].num_reg_images())
    registered = sorted(best.image(i).name for i in best.reg_image_ids())
    unregistered = sorted(set(names) - set(registered))
    needed = max(3, math.ceil(cfg["min_registered_fraction"] * len(names)))
    if len(registered) < needed:
        raise RadfieldError(
            f"{image_dir}: only {len(registered)} of {len(names)} images registered (need {needed}); "
            f"not registered: {_name_list(unregistered)}"
        )

    log(f"undistorting the {len(registered)} registered photos")
    t = time.perf_counter()
    pycolmap.undistort_images(
        work / "undistorted", work / "models" / str(best_id), image_dir, num_threads=int(cfg["num_threads"])
    )
    model = pycolmap.Reconstruction(work / "undistorted" / "sparse")
    center, scale = _normalization(model, cfg["target_radius"])
    model.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(), -scale * center))
    timings["undistort"] = time.perf_counter() - t

    result = work / "result"
    (result / "sparse").mkdir(parents=True)
    os.rename(work / "undistorted" / "images", result / "images")
    model.write_binary(result / "sparse")
    model.export_PLY(result / "points.ply")
    (result / NORMALIZATION_FILE).write_text(
        json.dumps({"center": center.tolist(), "scale": scale, "inverse": "x_sfm = x / scale + center"}, indent=2)
    )
    report = {
        "registered_images": len(registered),
        "total_images": len(names),
        "points": model.num_points3D(),
        "reprojection_error": float(best.compute_mean_reprojection_error()),
        "unregistered": unregistered,
        "camera_model": cfg["camera_model"],
        "shared_camera": one_size,
        "matcher": matcher,
        "seconds": {k: round(v, 2) for k, v in timings.items()},
    }
    (result / "sfm.json").write_text(json.dumps(report, indent=2))
    return report


def _extract(database: Path, image_dir: Path, names: list[str], mode: pycolmap.CameraMode, camera_model: str,
             cfg: dict) -> None:
    """SIFT features of the named images into a new COLMAP database, on the CPU; RadfieldError
    naming the images COLMAP could not read."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = int(cfg["num_threads"])
    extraction.use_gpu = False
    extraction.max_image_size = int(cfg["max_image_size"])
    extraction.sift.max_num_features = int(cfg["max_num_features"])
    pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=mode, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    with pycolmap.Database.open(database) as db:
        imported = {image.name for image in db.read_all_images()}
    unreadable = [n for n in names if n not in imported]
    if unreadable:
        raise RadfieldError(f"{image_dir}: COLMAP could not read {_name_list(unreadable)}")


def _match(database: Path, count: int, cfg: dict, log: Callable[[str], None]) -> str:
    """Match and verify the features of `count` images (exhaustive or sequential, see the module
    docstring); returns the matcher used."""
    import pycolmap

    threads = int(cfg["num_threads"])
    matcher = "exhaustive" if count <= cfg["exhaustive_max_images"] else "sequential"
    log(f"matching ({matcher})")
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    matching.use_gpu = False
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = int(cfg["sequential_overlap"])
        pairing.num_threads = threads
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                  device=pycolmap.Device.cpu)
    return matcher


def triangulate(cameras: list[Camera], images: Iterable[np.ndarray], cfg: dict, seed: int = 0,
                log: Callable[[str], None] = lambda _line: None) -> tuple[np.ndarray, np.ndarray]:
    """Sparse points (P, 3) and their colours (P, 3) in [0, 1] for a posed dataset without any:
    features matched across `images` (N, H, W, 3), or N images (H, W, 3) one at a time, float in
    [0, 1], undistorted, one per pinhole camera, are triangulated with the cameras held fixed
    (COLMAP's point triangulator), so the points are in the cameras' world frame. Settings: the
    `sfm` section `cfg`."""
    import pycolmap

    pycolmap.set_random_seed(seed)
    names = [f"{k:05d}.png" for k in range(len(cameras))]
    with tempfile.TemporaryDirectory(prefix="radfield-triangulate-") as scratch, _colmap_errors_only():
        work = Path(scratch)
        (work / "images").mkdir()
        (work / "model").mkdir()
        for name, image in zip(names, images):
            write_image(work / "images" / name, np.asarray(image))
        database = work / "database.db"
        log(f"extracting features from {len(names)} posed views")
        _extract(database, work / "images", names, pycolmap.CameraMode.PER_IMAGE, "PINHOLE", cfg)
        model = pycolmap.Reconstruction()
        with pycolmap.Database.open(database) as db:
            for image in db.read_all_images():
                cam = cameras[names.index(image.name)]
                # the known intrinsics, also for the geometric verification of the matches
                camera = pycolmap.Camera(model="PINHOLE", width=cam.width, height=cam.height,
                                         params=[cam.fx, cam.fy, cam.cx, cam.cy], camera_id=image.camera_id,
                                         has_prior_focal_length=True)
                db.update_camera(camera)
                model.add_camera_with_trivial_rig(camera)
                model.add_image_with_trivial_frame(
                    pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id),
                    pycolmap.Rigid3d(cam.w2c.double().numpy()[:3]))
        _match(database, len(names), cfg, log)
        log("triangulating with the known poses")
        model = pycolmap.triangulate_points(model, database, work / "images", work / "model")
    points = list(model.points3D.values())
    xyz = np.array([p.xyz for p in points], np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points], np.float64).reshape(-1, 3) / 255.0
    return xyz, rgb


def _normalization(model: pycolmap.Reconstruction, target_radius: float) -> tuple[np.ndarray, float]:
    """Centre = median of the sparse points (robust to stray points; for forward-facing captures
    it lies in the scene, not at the cameras); scale so that every camera centre lies within
    `target_radius` of it."""
    centers = np.array([model.image(i).projection_center() for i in model.reg_image_ids()])
    xyz = np.array([p.xyz for p in model.points3D.values()]) if model.num_points3D() else centers
    center = np.median(xyz, axis=0)
    radius = float(np.linalg.norm(centers - center, axis=1).max())
    return center, target_radius / max(radius, 1e-12)


def compare_poses(recovered: list[Camera], reference: list[Camera]) -> dict:
    """Align the recovered camera centres to the reference ones with a similarity transform
    (Umeyama, through COLMAP), then compare. Cameras are paired by file name without directory
    or extension ("images/0001.jpg" pairs with "0001").

    Returns `matched`, `scale` (reference units per recovered unit), `rotation_deg_{mean,median,max}`
    (angle between aligned and reference camera orientations) and `position_pct_{mean,median,max}`
    (centre distance as a percentage of the rig radius = mean distance of the reference centres
    from their centroid)."""
    import pycolmap

    by_name = {Path(c.name).stem: c for c in reference}
    pairs = [(c, by_name[Path(c.name).stem]) for c in recovered if Path(c.name).stem in by_name]
    if len(pairs) < 3:
        raise RadfieldError(f"compare_poses: only {len(pairs)} cameras share a file name, need 3")
    src = np.array([a.c2w[:3, 3].numpy() for a, _ in pairs])
    dst = np.array([b.c2w[:3, 3].numpy() for _, b in pairs])
    sim = pycolmap.estimate_sim3d(src, dst)
    if sim is None:
        raise RadfieldError("compare_poses: the camera centres are degenerate (collinear), no alignment")
    R, s = sim.rotation.matrix(), sim.scale
    aligned = s * src @ R.T + sim.translation
    radius = np.linalg.norm(dst - dst.mean(0), axis=1).mean()
    position = 100.0 * np.linalg.norm(aligned - dst, axis=1) / radius
    rel = np.array([b.c2w[:3, :3].numpy().T @ R @ a.c2w[:3, :3].numpy() for a, b in pairs])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rotation = np.degrees(np.arccos(cos))
    out = {"matched": len(pairs), "scale": float(s)}
    for key, values in (("rotation_deg", rotation), ("position_pct", position)):
        out |= {f"{key}_mean": float(values.mean()), f"{key}_median": float(np.median(values)),
                f"{key}_max": float(values.max())}
    return out


def _list_images(image_dir: Path) -> list[str]:
    if not image_dir.is_dir():
        raise RadfieldError(f"{image_dir}: not a folder of images")
    names = [p.name for p in list_images(image_dir)]
    if len(names) < 3:
        raise RadfieldError(f"{image_dir}: found {len(names)} images, structure from motion needs at least 3")
    return names


def _image_sizes(image_dir: Path, names: list[str]) -> dict[str, tuple[int, int]]:
    """(width, height) of every image from its header; names the files that cannot be opened."""
    import OpenImageIO as oiio

    sizes, unreadable = {}, []
    for name in names:
        inp = oiio.ImageInput.open(str(image_dir / name))
        if inp is None:
            oiio.geterror()  # clear the error state
            unreadable.append(name)
            continue
        sizes[name] = (inp.spec().width, inp.spec().height)
        inp.close()
    if unreadable:
        raise RadfieldError(f"{image_dir}: unreadable image files: {_name_list(unreadable)}")
    return sizes


def _name_list(names: list[str], limit: int = 10) -> str:
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def _replace_dir(src: Path, dst: Path) -> None:
    """Move the finished folder `src` to `dst`, replacing an older `dst` only once `src` is complete."""
    if dst.exists():
        old = dst.with_name(f".{dst.name}.old-{os.getpid()}")
        os.rename(dst, old)
        os.rename(src, dst)
        shutil.rmtree(old)
    else:
        os.rename(src, dst)


@contextlib.contextmanager
def _colmap_errors_only():
    """COLMAP logs every step at INFO level; keep only its errors (the stage logs the steps)."""
    import pycolmap

    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous
