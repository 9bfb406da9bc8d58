"""The coarse envelope (radfield.core.geometry.envelope): from points (pymeshlab) and as a visual hull."""

import cv2
import numpy as np
import pytest
import pyvista as pv
import torch

from radfield.core.geometry.cameras import Camera, look_at, pixel_rays
from radfield.errors import RadfieldError
from radfield.core.geometry.envelope import build_envelope, mesh_checks, overlay_picture, read_envelope, visual_hull, write_envelope


# ---------------------------------------------------------------- envelope and cage


# torus_envelope, torus_points, cfg: tests/conftest.py (shared with tests/test_cage.py)


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


def test_envelope_falls_back_when_reconstruction_is_open(torus_points, cfg):
    rng = np.random.default_rng(2)
    surface = torus_points(2000, rng)
    v, f, figures = build_envelope(surface, cfg("envelope", method="ball_pivoting", target_faces=300))
    assert figures["method"] in ("alpha", "convex")
    assert mesh_checks(v, f)["watertight"]
    assert _inside(surface, v, f).all()


def test_envelope_of_a_given_mesh(cfg):
    sphere = pv.Icosphere(radius=1.0, nsub=3)
    v, f, figures = build_envelope((sphere.points, sphere.regular_faces), cfg("envelope", target_faces=200, offset=0.05))
    radius = np.linalg.norm(v, axis=1)
    assert figures["faces"] <= 200 and figures["points_outside"] == 0
    assert radius.min() > 1.0 and radius.max() < 1.0 + 2.5 * figures["margin"]


def test_envelope_rejects_bad_input(cfg):
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


def test_visual_hull_of_a_sphere_and_overlay(tmp_path, cfg):
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


def test_visual_hull_errors(cfg):
    cameras, masks = _sphere_views()
    with pytest.raises(RadfieldError, match="masks"):
        visual_hull(cameras, masks[:-1], cfg("envelope"))
    # silhouettes without a common volume: the box fallback, around what the cameras look at
    v, f, figures = visual_hull(cameras, [np.zeros_like(m) for m in masks], cfg("envelope"))
    assert figures["fallback"] == figures["method"] == "box" and "no common volume" in figures["fallback_reason"]
    assert mesh_checks(v, f)["watertight"] and len(f) == 12 and _inside(np.zeros((1, 3)), v, f).all()
