"""The `studio` generated scene (path-tracer-like sampling, soft shadows, sky light, moderate
highlights) and the ray tracing it needs: rays with an origin each, jittered pixel samples, disc-light
samples. Tiny images: seconds."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from radfield.datasets import load_dataset, read_image
from radfield.demo.scenes import SCENES, orbit_cameras
from radfield.demo.static import generate_scene
from radfield.demo.raytrace import intersect, light_samples, pixel_offsets, render_view, shade

STUDIO = SCENES["studio"]


@pytest.fixture(scope="module")
def studio(tmp_path_factory):
    return generate_scene("studio", tmp_path_factory.mktemp("studio") / "studio", n_train=3, n_test=2, size=24)


def test_studio_views_rgba_and_determinism(studio, tmp_path):
    assert STUDIO.train_views == 100 and STUDIO.test_views == 20  # what `demo-scene studio` writes
    assert len(load_dataset(studio, "train")) == 3 and len(load_dataset(studio, "test")) == 2
    rgba = read_image(studio / "train" / "r_0.png")
    assert rgba.shape == (24, 24, 4)
    alpha = rgba[..., 3]
    assert 0.05 < alpha.mean() < 0.6 and alpha.max() == 1.0 and alpha.min() == 0.0
    # 64 rays per pixel: edge pixels take many coverage levels, not the 2x2 grid's five
    levels = np.unique(np.round(alpha * 64))
    assert len(levels) > 12
    again = generate_scene("studio", tmp_path / "again", n_train=3, n_test=2, size=24)
    for name in ("train/r_0.png", "train/r_2.png", "test/r_1.png", "scene.json"):
        assert (again / name).read_bytes() == (studio / name).read_bytes()
    other = generate_scene("studio", tmp_path / "other", n_train=3, n_test=2, size=24, seed=1)
    assert (other / "train" / "r_0.png").read_bytes() != (studio / "train" / "r_0.png").read_bytes()


def test_jittered_supersampling_approaches_the_pixel_area():
    """The coverage (alpha) of studio's 8x8 jittered rays is much closer to the pixel's area (a
    24x24 grid) than that of the 2x2 regular grid of the other scenes."""
    camera = orbit_cameras(100, 20, 32)[0][5]
    area = render_view(STUDIO, camera, samples=24, rng=np.random.default_rng(1))[0][..., 3]
    jittered = render_view(STUDIO, camera, rng=np.random.default_rng(2))[0][..., 3]
    grid2 = render_view(dataclasses.replace(STUDIO, samples=2, jitter=False), camera)[0][..., 3]
    edge = (area > 0) & (area < 1)
    assert edge.sum() > 50
    err_jittered, err_grid2 = (np.sqrt(((a - area)[edge] ** 2).mean()) for a in (jittered, grid2))
    assert err_jittered < 0.4 * err_grid2, (err_jittered, err_grid2)


def test_pixel_and_light_samples_are_stratified():
    rng = np.random.default_rng(0)
    off = pixel_offsets(4, True, 10, rng)
    cell = np.floor(off * 4).astype(int)
    assert (np.sort(cell[..., 0] * 4 + cell[..., 1], axis=1) == np.arange(16)).all()  # one ray per cell
    assert not np.allclose(off[0], off[1])  # jittered differently per pixel
    lighting = STUDIO.lighting
    dirs = light_samples(lighting, 64, 50, rng)
    centre = np.asarray(lighting.direction)
    angle = np.arccos(np.clip(dirs @ centre, -1, 1))
    assert np.allclose(np.linalg.norm(dirs, axis=-1), 1) and angle.max() <= lighting.radius + 1e-9
    assert angle.max() > 0.8 * lighting.radius  # fills the disc
    assert np.linalg.norm(dirs.mean(1) - centre, axis=-1).max() < 0.02  # stratified: every pixel's mean near the centre


def test_shapes_take_an_origin_per_ray():
    """intersect with one origin per ray agrees with intersect ray by ray from a shared origin."""
    rng = np.random.default_rng(3)
    origins = rng.normal(size=(4, 3)) * 0.5 + np.array([0.0, 0.0, 3.0])
    targets = rng.uniform(-0.6, 0.6, size=(200, 3)) + np.array([0.0, 0.0, -0.2])
    o = np.repeat(origins, 50, axis=0)
    d = targets - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, n, index = intersect(STUDIO, o, d)
    assert (index >= 0).sum() > 50 and len(set(index[index >= 0])) >= 4
    for k, origin in enumerate(origins):
        rows = slice(50 * k, 50 * (k + 1))
        t_k, n_k, i_k = intersect(STUDIO, origin, d[rows])
        assert np.array_equal(i_k, index[rows]) and np.allclose(t_k, t[rows]) and np.allclose(n_k, n[rows])


def test_soft_shadow_and_sky_light_on_the_floor():
    """A floor point right below the red sphere along the light is in its umbra: only the ambient
    (sky) light; a floor point in the open gets the sun too. Exact colours, from the shading rule."""
    floor, sphere = STUDIO.primitives[0], STUDIO.primitives[1]
    light = np.asarray(STUDIO.lighting.direction)
    top = max(floor.start[2], floor.end[2])  # the plinth's top cap
    s = (sphere.center[2] - top) / light[2]
    umbra = np.asarray(sphere.center) - s * light
    open_floor = np.array([0.75, -0.1, top])
    view = np.array([0.3, -0.6, 0.74]) / np.linalg.norm([0.3, -0.6, 0.74])
    o = np.stack([umbra, open_floor]) + 2 * view
    d = np.tile(-view, (2, 1))
    t, n, index = intersect(STUDIO, o, d)
    assert (index == 0).all() and np.allclose(n, [0, 0, 1])
    colour, specular = shade(STUDIO, o, d, t, n, index)
    albedo, ambient = np.asarray(floor.material.colour), STUDIO.lighting.ambient
    assert np.allclose(colour[0], albedo * ambient)  # n_z = 1: the sky term is the full ambient
    assert np.allclose(colour[1], albedo * (ambient + (1 - ambient) * light[2]))
    assert (specular == 0).all()
    # a surface facing sideways sees less sky: (1 + sky n_z) / (1 + sky)
    n_side = np.array([[1.0, 0.0, 0.0]])
    c_side, _ = shade(STUDIO, o[1] - 0.0, d[:1], t[1:], n_side, index[1:], light=-light[None])
    assert np.allclose(c_side[0], albedo * ambient / (1 + STUDIO.lighting.sky))


def test_studio_highlights_are_moderate_and_follow_the_view():
    glossy = [p.material for p in STUDIO.primitives if p.material.specular > 0]
    assert len(glossy) >= 3 and len(glossy) < len(STUDIO.primitives)  # a few glossy and some matte objects
    # lobes wide enough for SH degree 3: view-space width 2/sqrt(p) >= 20 degrees
    assert all(10 <= m.shininess <= 40 for m in glossy)
    assert all(math.degrees(2 / math.sqrt(m.shininess)) >= 20 for m in glossy)
    sphere = STUDIO.primitives[1]
    top = np.asarray(sphere.center) + np.array([0.0, 0.0, sphere.radius])
    light = np.asarray(STUDIO.lighting.direction)
    mirror = 2 * light[2] * np.array([0.0, 0.0, 1.0]) - light
    colours = []
    for eye in (top + 2 * mirror, top + 2 * light):  # the highlight's peak, then away from it
        d = ((top - eye) / np.linalg.norm(top - eye))[None]
        t, n, index = intersect(STUDIO, eye, d)
        colours.append(shade(STUDIO, eye, d, t, n, index)[1][0])
    assert colours[0] == pytest.approx(sphere.material.specular, rel=1e-3) and colours[1] < 0.05


def test_glossy_is_unchanged():
    """The study scene's images are as before `studio` (docs/studies/quality-omega0.md was measured on them):
    2x2 regular rays, no shadows, constant ambient, and one view's figures as recorded then."""
    glossy = SCENES["glossy"]
    assert glossy.samples == 2 and not glossy.jitter and not glossy.lighting.shadows and glossy.lighting.sky == 0
    camera = orbit_cameras(100, 20, 24)[0][7]
    rgba, depth = render_view(glossy, camera)
    assert np.allclose(rgba.reshape(-1, 4).mean(0), [0.093429, 0.092071, 0.083812, 0.192274], atol=2e-6)
    assert depth.sum() == pytest.approx(408.10797, abs=1e-3)
