"""Photo front end: SfM (pycolmap), envelope (pymeshlab, visual hull) and tetrahedral cage."""

import json
from pathlib import Path

import cv2
import meshio
import numpy as np
import pytest
import pyvista as pv
import torch

from radfield.core.geometry.cameras import Camera, look_at, opengl_to_opencv, pixel_rays
from radfield.errors import RadfieldError
from radfield.pipeline.config import load_defaults
from radfield.core.geometry.envelope import build_envelope, mesh_checks, overlay_picture, read_envelope, visual_hull, write_envelope
from radfield.datasets.colmap import read_colmap
from radfield.datasets.sfm import compare_poses, run_sfm
from radfield.core.geometry.cage import build_cage, locate_points, read_cage, sample_in_cage, tet_volumes, write_cage



def cfg(section: str, **overrides) -> dict:
    """A config section of pipeline.yaml with some keys changed."""
    return {**load_defaults()[section], **overrides}


def _fox_images(fox: Path, dst: Path, count: int, scale: float = 0.8) -> list[str]:
    """The first `count` fox_small photos (consecutive views), downscaled into `dst`."""
    dst.mkdir(parents=True, exist_ok=True)
    names = sorted(p.name for p in (fox / "images").glob("*.jpg"))[:count]
    for name in names:
        image = cv2.imread(str(fox / "images" / name))
        cv2.imwrite(str(dst / name), cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA))
    return names


def _noise_images(dst: Path, count: int, shape=(180, 240), seed: int = 0) -> list[str]:
    rng = np.random.default_rng(seed)
    dst.mkdir(parents=True, exist_ok=True)
    names = [f"noise{k}.png" for k in range(count)]
    for name in names:
        cv2.imwrite(str(dst / name), rng.integers(0, 256, (*shape, 3), dtype=np.uint8))
    return names


def _leftovers(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if ".tmp-" in p.name or ".old-" in p.name]


# ---------------------------------------------------------------- SfM


def test_sfm_registers_a_tiny_real_capture(tmp_path, fox):
    names = _fox_images(fox, tmp_path / "photos", 8)
    out = tmp_path / "sfm"
    figures = run_sfm(tmp_path / "photos", out, cfg("sfm", num_threads=2))

    assert figures["total_images"] == 8 and figures["registered_images"] == 8
    assert figures["points"] > 200
    assert 0 < figures["reprojection_error"] < 1.5
    assert sorted(p.name for p in (out / "images").iterdir()) == names
    assert {"cameras.bin", "images.bin", "points3D.bin"} <= {p.name for p in (out / "sparse").iterdir()}
    assert (out / "points.ply").stat().st_size > 0
    assert json.loads((out / "sfm.json").read_text())["matcher"] == "exhaustive"
    assert not _leftovers(tmp_path)

    cameras = [view.camera for view in read_colmap(out, "all")[0]]  # the output is a COLMAP dataset
    assert [c.name for c in cameras] == [Path(n).stem for n in names]
    # normalised: every camera centre within the target radius 1 of the points' median
    assert max(float(c.center.norm()) for c in cameras) == pytest.approx(1.0, abs=1e-6)
    norm = json.loads((out / "normalization.json").read_text())
    assert len(norm["center"]) == 3 and norm["scale"] > 0

    meta = json.loads((fox / "transforms.json").read_text())
    reference = [
        Camera(meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"], int(meta["w"]), int(meta["h"]),
               opengl_to_opencv(torch.tensor(f["transform_matrix"])), f["file_path"])
        for f in meta["frames"]
    ]
    errors = compare_poses(cameras, reference)
    assert errors["matched"] == 8
    assert errors["rotation_deg_max"] < 3.0
    assert errors["position_pct_max"] < 5.0


def test_sfm_sequential_matching_for_larger_sets(tmp_path, fox):
    _fox_images(fox, tmp_path / "photos", 8, scale=0.6)
    (tmp_path / "sfm").mkdir()
    (tmp_path / "sfm" / "stale.txt").write_text("from an older run")
    figures = run_sfm(tmp_path / "photos", tmp_path / "sfm", cfg("sfm", exhaustive_max_images=4, sequential_overlap=3))
    assert figures["registered_images"] == 8
    assert not (tmp_path / "sfm" / "stale.txt").exists() and not _leftovers(tmp_path)  # replaced whole
    assert json.loads((tmp_path / "sfm" / "sfm.json").read_text())["matcher"] == "sequential"


def test_sfm_needs_three_images(tmp_path):
    _noise_images(tmp_path / "photos", 2)
    with pytest.raises(RadfieldError, match="found 2 images"):
        run_sfm(tmp_path / "photos", tmp_path / "sfm", cfg("sfm"))


def test_sfm_names_unreadable_images(tmp_path):
    _noise_images(tmp_path / "photos", 3)
    (tmp_path / "photos" / "broken.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(RadfieldError, match="broken.jpg"):
        run_sfm(tmp_path / "photos", tmp_path / "sfm", cfg("sfm"))
    assert not (tmp_path / "sfm").exists()


def test_sfm_images_without_overlap_fail_cleanly(tmp_path):
    _noise_images(tmp_path / "photos", 5)
    out = tmp_path / "sfm"
    out.mkdir()
    (out / "previous.txt").write_text("an earlier good run")
    with pytest.raises(RadfieldError, match="do not overlap") as info:
        run_sfm(tmp_path / "photos", out, cfg("sfm"))
    assert "\n" not in str(info.value)
    assert [p.name for p in out.iterdir()] == ["previous.txt"]  # the earlier output is untouched
    assert not _leftovers(tmp_path)


def test_sfm_lists_unregistered_images(tmp_path, fox):
    names = _fox_images(fox, tmp_path / "photos", 6)
    shape = cv2.imread(str(tmp_path / "photos" / names[0])).shape[:2]  # same size: one shared camera
    noise = _noise_images(tmp_path / "photos", 3, shape)
    with pytest.raises(RadfieldError, match="only 6 of 9 images registered") as info:
        run_sfm(tmp_path / "photos", tmp_path / "sfm", cfg("sfm", min_registered_fraction=0.9))
    assert all(name in str(info.value) for name in noise)
    assert not (tmp_path / "sfm").exists()


def test_compare_poses_undoes_a_similarity():
    rng = np.random.default_rng(1)
    reference = [Camera(100, 100, 50, 50, 100, 100, look_at(3 * np.r_[np.cos(a), np.sin(a), 0.5], (0, 0, 0)), f"dir/{k}.png")
                 for k, a in enumerate(np.linspace(0, 2 * np.pi, 10, endpoint=False))]
    R = torch.tensor(cv2.Rodrigues(rng.normal(size=3))[0])
    sim = torch.eye(4, dtype=torch.float64)
    sim[:3, :3], sim[:3, 3] = 0.3 * R, torch.tensor([1.0, -2.0, 0.5])
    recovered = []
    for k, cam in enumerate(reference):
        c2w = sim @ cam.c2w
        c2w[:3, :3] /= 0.3
        if k == 4:  # one camera turned by 5 degrees about its own optical axis
            c2w[:3, :3] = c2w[:3, :3] @ torch.tensor(cv2.Rodrigues(np.r_[0, 0, np.radians(5)])[0])
        recovered.append(Camera(100, 100, 50, 50, 100, 100, c2w, Path(cam.name).name))
    errors = compare_poses(recovered, reference)
    assert errors["matched"] == 10
    assert errors["scale"] == pytest.approx(1 / 0.3)
    assert errors["position_pct_max"] < 1e-6
    assert errors["rotation_deg_max"] == pytest.approx(5.0, abs=1e-6)
    assert errors["rotation_deg_median"] < 1e-6


# ---------------------------------------------------------------- envelope and cage


def _torus(n, rng, R=1.0, r=0.35):
    u, w = rng.uniform(0, 2 * np.pi, (2, n))
    return np.stack([(R + r * np.cos(w)) * np.cos(u), (R + r * np.cos(w)) * np.sin(u), r * np.sin(w)], 1)


@pytest.fixture(scope="module")
def torus_envelope():
    """Envelope of 3000 torus samples plus 40 floaters 2.5-3.5 from the centre."""
    rng = np.random.default_rng(0)
    surface = _torus(3000, rng)
    direction = rng.normal(size=(40, 3))
    floaters = direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(2.5, 3.5, (40, 1))
    v, f, figures = build_envelope(np.concatenate([surface, floaters]), cfg("envelope", target_faces=400))
    return surface, v, f, figures


def _inside(points, v, f):
    """Independent inside test (VTK's vtkSelectEnclosedPoints, not the implicit distance the
    envelope code uses)."""
    marked = pv.PolyData(points).select_interior_points(pv.PolyData.from_regular_faces(v, f), method="cell_locator")
    return np.asarray(marked["selected_points"], bool)


def test_envelope_encloses_points_and_drops_outliers(torus_envelope, tmp_path):
    surface, v, f, figures = torus_envelope
    assert figures["method"] == "poisson"
    assert figures["outliers"] >= 40
    assert 360 <= figures["faces"] <= 400 and figures["faces"] == len(f)
    checks = mesh_checks(v, f)
    assert checks["watertight"] and checks["self_intersections"] == 0
    assert _inside(surface, v, f).all()
    # the floaters did not inflate it: it hugs the torus (|xy| <= 1.35, |z| <= 0.35) within a margin
    assert np.abs(v[:, :2]).max() < 1.35 + 2 * figures["margin"]
    assert np.abs(v[:, 2]).max() < 0.35 + 2 * figures["margin"]

    write_envelope(tmp_path / "envelope.ply", v, f)
    rv, rf = read_envelope(tmp_path / "envelope.ply")
    assert np.array_equal(rf, f) and np.allclose(rv, v, atol=1e-5)


def test_envelope_falls_back_when_reconstruction_is_open():
    rng = np.random.default_rng(2)
    surface = _torus(2000, rng)
    v, f, figures = build_envelope(surface, cfg("envelope", method="ball_pivoting", target_faces=300))
    assert figures["method"] in ("alpha", "convex")
    assert mesh_checks(v, f)["watertight"]
    assert _inside(surface, v, f).all()


def test_envelope_of_a_given_mesh():
    sphere = pv.Icosphere(radius=1.0, nsub=3)
    v, f, figures = build_envelope((sphere.points, sphere.regular_faces), cfg("envelope", target_faces=200, offset=0.05))
    radius = np.linalg.norm(v, axis=1)
    assert figures["faces"] <= 200 and figures["points_outside"] == 0
    assert radius.min() > 1.0 and radius.max() < 1.0 + 2.5 * figures["margin"]


def test_envelope_rejects_bad_input():
    with pytest.raises(RadfieldError, match="at least 10"):
        build_envelope(np.zeros((5, 3)), cfg("envelope"))
    with pytest.raises(RadfieldError, match=r"\(N, 3\)"):
        build_envelope(np.full((20, 3), np.nan), cfg("envelope"))


def _sphere_views(radius=0.5, size=64):
    """Cameras around a sphere at the origin and its exact silhouettes."""
    directions = [(np.cos(a), np.sin(a), 0.3) for a in np.linspace(0, 2 * np.pi, 10, endpoint=False)]
    directions += [(0, 0.1, 1), (0.1, 0, -1)]
    cameras, masks = [], []
    for k, d in enumerate(directions):
        d = np.array(d) / np.linalg.norm(d)
        eye = 2.5 * d
        up = (0, 0, 1) if abs(d[2]) < 0.9 else (0, 1, 0)
        cam = Camera(60.0, 60.0, size / 2, size / 2, size, size, look_at(eye, (0, 0, 0), up=up), f"v{k}")
        rays, _ = pixel_rays(cam, dtype=torch.float64)
        along = rays.numpy() @ -eye
        masks.append(eye @ eye - along**2 <= radius**2)  # the ray passes within `radius` of the centre
        cameras.append(cam)
    return cameras, masks


def test_visual_hull_of_a_sphere_and_overlay(tmp_path):
    cameras, masks = _sphere_views()
    v, f, figures = visual_hull(cameras, masks, cfg("envelope", target_faces=500))
    assert 450 <= figures["faces"] <= 500
    assert mesh_checks(v, f)["watertight"]
    radius = np.linalg.norm(v, axis=1)
    assert radius.min() > 0.5  # encloses the sphere ...
    assert radius.max() < 0.5 + figures["margin"] + 0.15  # ... and is not much larger
    rng = np.random.default_rng(3)
    on_sphere = rng.normal(size=(2000, 3))
    assert _inside(0.5 * on_sphere / np.linalg.norm(on_sphere, axis=1, keepdims=True), v, f).all()

    image = np.dstack([masks[0] * 0.8] * 3).astype(np.float32)
    picture = overlay_picture(v, f, cameras[0], image, tmp_path / "overlay.png")
    assert picture.shape == (64, 64, 3) and picture.dtype == np.uint8
    changed = (picture.astype(int) != np.round(image * 255).astype(int)).any(-1)
    assert changed[masks[0]].all()  # the envelope's silhouette covers the object's
    assert cv2.imread(str(tmp_path / "overlay.png")).shape == (64, 64, 3)


def test_visual_hull_errors():
    cameras, masks = _sphere_views()
    with pytest.raises(RadfieldError, match="masks"):
        visual_hull(cameras, masks[:-1], cfg("envelope"))
    # silhouettes without a common volume: the box fallback, around what the cameras look at
    v, f, figures = visual_hull(cameras, [np.zeros_like(m) for m in masks], cfg("envelope"))
    assert figures["fallback"] == figures["method"] == "box" and "no common volume" in figures["fallback_reason"]
    assert mesh_checks(v, f)["watertight"] and len(f) == 12 and _inside(np.zeros((1, 3)), v, f).all()


@pytest.fixture(scope="module")
def torus_cage(torus_envelope):
    _, v, f, _ = torus_envelope
    return build_cage(v, f, cfg("tetra"))


def test_cage_is_coarse_positive_and_round_trips(torus_envelope, torus_cage, tmp_path):
    surface = torus_envelope[0]
    cv, tets, figures = torus_cage
    assert 100 <= figures["tets"] <= 5000 and figures["tets"] == len(tets)
    assert figures["vertices"] == len(cv) and np.unique(tets).size == len(cv)
    assert (tet_volumes(cv, tets) > 0).all()
    index, _ = locate_points(cv, tets, surface)
    assert (index >= 0).all()  # every surface sample is inside the cage

    write_cage(tmp_path, cv, tets)
    for name in ("cage.vtk", "cage.npz"):
        rv, rt = read_cage(tmp_path / name)
        assert np.array_equal(rt, tets) and np.array_equal(rv, cv)
    assert meshio.read(tmp_path / "cage.vtk").cells_dict["tetra"].shape == tets.shape

    # a user moves vertices in another tool and saves: same topology, new positions
    moved = cv + np.array([0.0, 0.0, 0.1]) * cv[:, :1]
    meshio.write(tmp_path / "edited.vtu", meshio.Mesh(moved, [("tetra", tets)]))
    rv, rt = read_cage(tmp_path / "edited.vtu")
    assert np.array_equal(rt, tets) and np.allclose(rv, moved)


def test_read_cage_errors(tmp_path):
    (tmp_path / "junk.vtk").write_text("garbage")
    with pytest.raises(RadfieldError, match="junk.vtk"):
        read_cage(tmp_path / "junk.vtk")
    np.savez(tmp_path / "bad.npz", vertices=np.zeros((3, 3)), tets=np.array([[0, 1, 2, 3]]))
    with pytest.raises(RadfieldError, match="indices"):
        read_cage(tmp_path / "bad.npz")


def test_locate_points_is_exact(torus_cage):
    cv, tets, _ = torus_cage
    rng = np.random.default_rng(4)
    lo, hi = cv.min(0), cv.max(0)
    points = rng.uniform(lo - 0.1, hi + 0.1, (20000, 3))
    index, bary = locate_points(cv, tets, points, k=4)
    inside = index >= 0
    assert 0.1 < inside.mean() < 0.9
    assert np.allclose(np.einsum("nk,nkd->nd", bary[inside], cv[tets[index[inside]]]), points[inside])
    assert np.allclose(bary[inside].sum(1), 1) and (bary[inside] >= -1e-9).all()
    # brute force on a subset: a point is inside iff some tet has all barycentrics >= 0
    corners = cv[tets]
    T = np.linalg.inv(np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1)))
    for p, i in zip(points[:400], index[:400]):
        b = np.einsum("tij,tj->ti", T, p - corners[:, 0])
        holds = (b >= -1e-9).all(1) & (b.sum(1) <= 1 + 1e-9)
        assert holds.any() == (i >= 0)
        if i >= 0:
            assert holds[i]


def test_sample_in_cage_is_volume_weighted(torus_cage):
    cv, tets, figures = torus_cage
    points, index, bary = sample_in_cage(cv, tets, 40000, rng=5)
    assert np.allclose(np.einsum("nk,nkd->nd", bary, cv[tets[index]]), points)
    located, _ = locate_points(cv, tets, points)
    assert (located >= 0).all()
    volumes = tet_volumes(cv, tets)
    centroid = (volumes[:, None] * cv[tets].mean(1)).sum(0) / volumes.sum()
    spread = points.std(0) / np.sqrt(len(points))
    assert np.all(np.abs(points.mean(0) - centroid) < 5 * spread)
    # the largest tets get proportionally more samples
    big = volumes > np.median(volumes)
    assert np.isin(index, np.flatnonzero(big)).mean() == pytest.approx(volumes[big].sum() / volumes.sum(), abs=0.01)


def test_run_layout_names_the_normalization_file_sfm_writes():
    from radfield.datasets import sfm
    from radfield.pipeline import info

    assert info.NORMALIZATION_FILE == sfm.NORMALIZATION_FILE
