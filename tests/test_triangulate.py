"""The triangulate stage and the starts it serves, on fern (../shared/datasets/fern: 17 posed training
photos, no points, no alpha) at 1/4 of its 504x378 (126x94, so the whole front end takes seconds): its
points, the init stage starting from them (capped by init.footprint_px: fern is forward-facing),
and the random fallback's few-pixel primitives."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from radfield.core.geometry.cameras import Camera, axes_half_angle, look_at
from radfield.datasets.scene import load_scene
from radfield.model_file import load_model
from radfield.pipeline.config import load_config
from radfield.pipeline.info import format_info, run_info
from radfield.pipeline.runner import read_manifest, run_pipeline
from radfield.stages import init
from radfield.stages.registry import stages

SETS = ["data.downscale=4", "envelope.source=none", "init.num_points=300"]


def run_until(stage: str, fern: Path, run_dir: Path, *sets: str) -> dict[str, str]:
    return run_pipeline(stages(), run_dir, load_config(sets=[*SETS, *sets]), input_path=fern, until_stage=stage,
                        quiet=True)


def projected_radii(run_dir: Path, model=None) -> np.ndarray:
    """(views, primitives): each primitive's scale (of `model`, else the init stage's) in pixels of each
    training view (NaN where it lies behind the camera)."""
    model = model or load_model(run_dir / "init" / init.INIT_MODEL)
    means, radius = model.means.double().numpy(), model.log_scales.exp().max(1).values.double().numpy()
    out = []
    for camera in load_scene(run_dir / "data" / "scene.json").cameras("train"):
        depth = means @ camera.w2c.double().numpy()[2, :3] + camera.w2c.double().numpy()[2, 3]
        out.append(np.where(depth > 0, radius * max(camera.fx, camera.fy) / np.where(depth > 0, depth, 1), np.nan))
    return np.array(out)


@pytest.fixture(scope="module")
def fern_run(tmp_path_factory, shared_dataset) -> tuple[Path, Path]:
    """(fern, a run of it up to init with the default start)."""
    fern = shared_dataset("fern", "transforms.json")
    run_dir = tmp_path_factory.mktemp("fern") / "run"
    status = run_until("init", fern, run_dir)
    assert status == {"sfm": "not applicable", "data": "ran", "triangulate": "ran", "envelope": "not applicable",
                      "tetra": "not applicable", "init": "ran"}
    return fern, run_dir


@pytest.fixture(scope="module")
def uncapped_run(fern_run, tmp_path_factory) -> Path:
    """fern_run's start without the footprint cap (init.footprint_px=0)."""
    fern, default_run = fern_run
    run_dir = tmp_path_factory.mktemp("uncapped") / "run"
    shutil.copytree(default_run, run_dir)   # the triangulation cached: only init runs again
    assert run_until("init", fern, run_dir, "init.footprint_px=0")["init"] == "ran"
    assert "footprint_px" not in read_manifest(run_dir / "init")["figures"]
    return run_dir


def test_posed_photos_without_points_are_triangulated_once(fern_run):
    _, run_dir = fern_run
    figures = read_manifest(run_dir / "triangulate")["figures"]
    assert figures["views"] == 17 and figures["points"] > 150   # 320 measured
    with np.load(run_dir / "triangulate" / "triangulated.npz") as triangulated:
        xyz, rgb = triangulated["xyz"], triangulated["rgb"]
    assert xyz.shape == rgb.shape == (figures["points"], 3) and 0 <= rgb.min() and rgb.max() <= 1
    assert rgb.std(0).min() > 0.03   # the features' colours, not one grey
    # in the dataset's world frame: in front of the first camera, most of them inside its view
    camera = load_scene(run_dir / "data" / "scene.json").cameras("train")[0]
    local = xyz @ camera.w2c[:3, :3].double().numpy().T + camera.w2c[:3, 3].double().numpy()
    u, v = (local @ camera.K.double().numpy().T)[:, :2].T / local[:, 2]
    seen = (local[:, 2] > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    assert seen.mean() > 0.5


def test_init_starts_from_the_triangulated_points_with_small_primitives(fern_run, uncapped_run):
    _, run_dir = fern_run
    info = run_info(run_dir)
    assert info["stages"]["init"]["source"] == "triangulate" and info["stages"]["init"]["footprint_px"] == 12
    assert "source=triangulate" in format_info(info)
    model = load_model(run_dir / "init" / init.INIT_MODEL)
    with np.load(run_dir / "triangulate" / "triangulated.npz") as triangulated:
        xyz = triangulated["xyz"]
    means = model.means.double().numpy()
    assert len(means) == 300 and (np.abs(means[:, None] - xyz[None]).max(-1) < 1e-5).any(1).all()  # a subset
    # coloured from the points, sized by their spacing: far smaller than 300 random centres sized by theirs
    # (the random start before RANDOM_FOOTPRINT_PX; measured: a median 22 px against 111 px in 126 px views)
    assert model.sh[:, 0].std(0).min() > 0.05
    scene = load_scene(run_dir / "data" / "scene.json")
    _, means, _ = init.initial_centres(scene, {}, "random", 300, np.random.default_rng(0))
    spread = init.make_primitives(means, None, "neural", 0, scene.extent, 0, {"window": model.window})
    assert np.nanmedian(projected_radii(uncapped_run)) < 0.5 * np.nanmedian(projected_radii(run_dir, spread))


def assert_capped(radii: np.ndarray, uncapped: np.ndarray, cap: float) -> None:
    """No primitive larger than `cap` pixels in any view that has it in front, the larger ones at
    it, the smaller ones as they were without the cap."""
    largest = np.nanmax(uncapped, 0)   # each primitive's radius in pixels where it looks largest
    assert np.nanmax(radii) <= cap * (1 + 1e-4)   # float32 scales
    assert np.allclose(np.nanmax(radii, 0)[largest > cap], cap, rtol=1e-4)
    small = largest < cap
    assert small.any() and np.allclose(radii[:, small], uncapped[:, small], equal_nan=True)


def test_a_forward_facing_start_is_capped_by_default(fern_run, uncapped_run):
    # fern is forward-facing: its training views' optical axes lie within init.footprint_cone (20°) of
    # their mean, so the default caps its start at init.footprint_px (12 px)
    _, run_dir = fern_run
    assert 3 < axes_half_angle(load_scene(run_dir / "data" / "scene.json").cameras("train")) < 20   # 9.9° measured
    uncapped = projected_radii(uncapped_run)
    figures = read_manifest(run_dir / "init")["figures"]
    assert figures["footprint_px"] == 12 and figures["footprint_capped"] == (np.nanmax(uncapped, 0) > 12).sum() > 0
    assert_capped(projected_radii(run_dir), uncapped, 12)


def test_init_footprint_cone_tells_a_forward_facing_capture(fern_run, uncapped_run, tmp_path):
    fern, _ = fern_run
    uncapped = projected_radii(uncapped_run)
    cap = float(np.round(np.nanmedian(np.nanmax(uncapped, 0))))   # half the primitives larger
    angle = axes_half_angle(load_scene(uncapped_run / "data" / "scene.json").cameras("train"))
    run_dir = tmp_path / "run"
    shutil.copytree(uncapped_run, run_dir)
    # a cone just wider than fern's views caps, one just narrower does not
    for cone, capped in ((angle + 0.5, True), (angle - 0.5, False)):
        sets = (f"init.footprint_px={cap}", f"init.footprint_cone={cone}")
        assert run_until("init", fern, run_dir, *sets)["init"] == "ran"
        figures = read_manifest(run_dir / "init")["figures"]
        assert figures["source"] == "triangulate" and ("footprint_px" in figures) == capped
        if capped:
            assert figures["footprint_px"] == cap and figures["footprint_capped"] == (np.nanmax(uncapped, 0) > cap).sum()
            assert_capped(projected_radii(run_dir), uncapped, cap)
        else:
            assert np.array_equal(projected_radii(run_dir), uncapped, equal_nan=True)


def test_axes_half_angle_of_views_around_an_object():
    # 8 views on a ring 30° above the origin, all looking at it: every axis 60° from straight down
    ring = [Camera(50.0, 50.0, 32.0, 32.0, 64, 64, look_at((np.cos(a), np.sin(a), np.tan(np.pi / 6)), (0.0, 0.0, 0.0)))
            for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
    assert axes_half_angle(ring) == pytest.approx(60.0, abs=1e-6)
    # two views from one place, 7° to either side of the x axis: a forward-facing pair
    pair = [Camera(50.0, 50.0, 32.0, 32.0, 64, 64, look_at((0.0, 0.0, 0.0), (1.0, np.tan(t), 0.0)))
            for t in np.radians([-7.0, 7.0])]
    assert axes_half_angle(pair) == pytest.approx(7.0, abs=1e-6)
    assert axes_half_angle(ring[:1]) == 0.0


def test_the_random_start_covers_a_few_pixels(fern_run, tmp_path):
    fern, run_dir = fern_run
    status = run_until("init", fern, run_dir, "init.source=random")
    assert status["triangulate"] == "cached" and status["init"] == "ran"
    figures = read_manifest(run_dir / "init")["figures"]
    assert figures["source"] == "random" and figures["footprint_px"] == init.RANDOM_FOOTPRINT_PX
    radii = projected_radii(run_dir)
    radii = radii[:, ~np.isnan(radii).all(0)]   # the centres that some training view has in front
    # at most the footprint in every view that has it in front; most primitives at it exactly
    assert np.nanmax(radii) <= init.RANDOM_FOOTPRINT_PX * (1 + 1e-4)   # float32 scales
    assert np.median(np.nanmax(radii, 0)) > 0.9 * init.RANDOM_FOOTPRINT_PX
