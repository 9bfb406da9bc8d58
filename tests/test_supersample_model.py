"""A model trained with render.supersample = n records n (model file metadata `supersample`), and
every command that draws a model file draws it with n × n rays per pixel (core/antialias.render_model)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from radfield.core.render.antialias import render_model, render_supersampled
from radfield.delivery.bake import coverage
from radfield.core.geometry.cameras import Camera, look_at
from radfield.delivery.export import supersample_warning
from radfield.model_file import load_model, read_metadata, save_model
from radfield.core.kinds import random_gaussians, random_neural, rotmat_to_quat
from radfield.datasets.images import read_image
from radfield.datasets.scene import Normalization, load_split
from radfield.demo.static import generate_scene
from radfield.edit.compose import concat_prims
from radfield.edit.affine import deform_field
from radfield.edit.field import Field, box_cage
from radfield.pipeline.config import load_defaults
from radfield.run import Run
from radfield.stages.train import to_normalized, to_world
from radfield.delivery.viewer import Viewer, viser_camera

BG = (1.0, 1.0, 1.0)


def model(n: int = 2, seed: int = 1):
    return replace(random_neural(40, extent=0.5, scale=0.2, seed=seed), supersample=n)


def camera(size: int = 16) -> Camera:
    return Camera(1.3 * size, 1.3 * size, size / 2, size / 2, size, size, look_at((0.4, -2.5, 0.8), (0, 0, 0)))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return generate_scene("blobs", tmp_path_factory.mktemp("data") / "blobs", n_train=3, n_test=2, size=16)


@pytest.fixture(scope="module")
def test_views(data):
    """The test cameras of `data` as `radfield render` / `eval` of a model file see them, and their photos."""
    split = load_split(data, "test", load_defaults()["data"])
    return split.cameras, split


def drawn(prims, cameras, n: int) -> list[np.ndarray]:
    with torch.no_grad():
        return [render_supersampled(prims, c, n, background=BG).color.clamp(0, 1).numpy() for c in cameras]


# --- the file ---------------------------------------------------------------------------------

@pytest.mark.parametrize("make", [model, lambda n: replace(random_gaussians(20, seed=2), supersample=n)])
def test_supersample_round_trips_and_is_absent_at_1(tmp_path, make):
    save_model(tmp_path / "two.safetensors", make(2))
    assert read_metadata(tmp_path / "two.safetensors")["supersample"] == "2"
    assert load_model(tmp_path / "two.safetensors").supersample == 2
    save_model(tmp_path / "one.safetensors", make(1))
    assert "supersample" not in read_metadata(tmp_path / "one.safetensors")
    assert load_model(tmp_path / "one.safetensors").supersample == 1
    # n = 1 writes the bytes of a file that never had the key (old files keep their hashes)
    save_model(tmp_path / "default.safetensors", replace(make(1), supersample=1))
    assert (tmp_path / "one.safetensors").read_bytes() == (tmp_path / "default.safetensors").read_bytes()


def test_the_helpers_that_rebuild_primitives_keep_it():
    prims = model(3)
    assert prims.to(dtype=torch.float64).supersample == 3
    assert prims.select(torch.arange(5)).supersample == 3
    assert prims.map(lambda t: t * 1).supersample == 3
    norm = Normalization(center=torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64), scale=2.0)
    assert to_world(to_normalized(prims, norm), norm).supersample == 3
    assert concat_prims(model(1), model(2, seed=3)).supersample == 2  # compose: the larger
    assert concat_prims(model(2), model(1, seed=3)).supersample == 2


@pytest.mark.parametrize("value", ["7", "0", "two", "1.5"])
def test_a_bad_value_is_a_one_line_error(tmp_path, cli, data, value):
    bad = tmp_path / "bad.safetensors"
    save_model(bad, model(1), extra={"supersample": value})
    code, _, err = cli("render", bad, "-d", data, "-o", tmp_path / "frames", "-q")
    assert code == 1 and len(err.strip().splitlines()) == 1, err
    assert err.startswith("radfield: error:") and "supersample" in err and "Traceback" not in err
    assert not (tmp_path / "frames").exists()


# --- the consumers ----------------------------------------------------------------------------

def test_render_and_eval_of_a_model_file_draw_n_rays_per_pixel(tmp_path, cli, data, test_views):
    cameras, split = test_views
    prims = model(2)
    save_model(tmp_path / "m.safetensors", prims)
    at1, at2 = drawn(prims, cameras, 1), drawn(prims, cameras, 2)
    assert max(np.abs(a - b).max() for a, b in zip(at1, at2)) > 0.05  # n matters for this model

    code, _, err = cli("render", tmp_path / "m.safetensors", "-d", data, "-o", tmp_path / "frames", "-q")
    assert code == 0, err
    for c, want in zip(cameras, at2):
        png = read_image(tmp_path / "frames" / f"{c.name}.png")[..., :3]
        assert np.abs(png - want).max() <= 1 / 255 + 1e-6

    code, _, err = cli("eval", tmp_path / "m.safetensors", "-d", data, "-o", tmp_path / "report", "-q")
    assert code == 0, err
    for c, want in zip(cameras, at2):  # eval's renders are the model's n = 2 images too
        png = read_image(tmp_path / "report" / "renders" / f"{c.name}.png")[..., :3]
        assert np.abs(png - want).max() <= 1 / 255 + 1e-6


def test_an_edited_model_keeps_n_and_is_rendered_with_it(tmp_path, cli, data, test_views):
    save_model(tmp_path / "m.safetensors", model(2))
    code, _, err = cli("edit", tmp_path / "m.safetensors", "-o", tmp_path / "edited", "--translate", "0.05,0,0", "-q")
    assert code == 0, err
    run = Run.open(tmp_path / "edited")
    assert run.is_edited
    edited = load_model(run.model)
    assert edited.supersample == 2
    # the edited run itself (edited from a model file: no config, no dataset of its own)
    code, _, err = cli("render", tmp_path / "edited", "-o", tmp_path / "frames", "-q")
    assert code == 1 and "--dataset is required" in err and "Traceback" not in err
    code, _, err = cli("render", tmp_path / "edited", "-d", data, "-o", tmp_path / "frames", "-q")
    assert code == 0, err
    cameras, _ = test_views
    for c, want in zip(cameras, drawn(edited, cameras, 2)):
        png = read_image(tmp_path / "frames" / f"{c.name}.png")[..., :3]
        assert np.abs(png - want).max() <= 1 / 255 + 1e-6


def test_a_deformation_that_splits_primitives_keeps_n():
    prims = model(2)
    vertices, tets = box_cage((-1, -1, -1), (1, 1, 1), 2)
    fld = Field(prims, vertices, tets)
    fld.rebind()
    twist = vertices.copy()
    angle = 0.8 * vertices[:, 2]  # a twist about z: the maps vary from tet to tet, so some primitives split
    twist[:, 0] = vertices[:, 0] * np.cos(angle) - vertices[:, 1] * np.sin(angle)
    twist[:, 1] = vertices[:, 0] * np.sin(angle) + vertices[:, 1] * np.cos(angle)
    out = deform_field(fld, twist, split=0.05)
    assert len(out.prims) > len(prims)  # the rebuilding path (children joined to the rest) ran
    assert out.prims.supersample == 2


def test_bake_keeps_n_and_measures_coverage_with_its_rays(tmp_path, cli, data):
    prims = model(2)
    save_model(tmp_path / "m.safetensors", prims)
    code, _, err = cli("bake", tmp_path / "m.safetensors", "-d", data, "-o", tmp_path / "baked.safetensors", "-q")
    assert code == 0, err
    assert load_model(tmp_path / "baked.safetensors").supersample == 2
    assert json.loads(read_metadata(tmp_path / "baked.safetensors")["baked"])["primitives_before"] == len(prims)
    # coverage at n = 2 sums each pixel's mean over its 2 × 2 rays: the n = 1 coverage of the
    # 2×-resolution view, divided by 4
    cams = [camera(), camera(12)]
    fine = coverage(replace(prims, supersample=1), [c.scaled(2) for c in cams], background=BG)
    assert torch.allclose(coverage(prims, cams, background=BG), fine / 4, atol=1e-5)
    assert not torch.allclose(coverage(replace(prims, supersample=1), cams, background=BG), fine / 4, atol=1e-3)


def test_the_viewer_draws_n_rays_per_pixel():
    prims = model(2)
    c = camera(16)
    wxyz = rotmat_to_quat(c.c2w[:3, :3][None])[0].numpy()
    client = SimpleNamespace(camera=SimpleNamespace(wxyz=wxyz, position=c.c2w[:3, 3].numpy(),
                                                    fov=2 * math.atan(8 / c.fy), aspect=1.0))
    viewer = SimpleNamespace(scene=SimpleNamespace(model=prims, background=BG), time=None, light=None)
    viewer.render_view = lambda camera, moment, light: Viewer.render_view(viewer, camera, moment, light)
    frame = Viewer.render_frame(viewer, client, 16)  # the methods, without a server or a browser
    same = viser_camera(wxyz, c.c2w[:3, 3].numpy(), 2 * math.atan(8 / c.fy), 1.0, 16)
    with torch.no_grad():
        want = {n: (render_supersampled(prims, same, n, background=BG).color.clamp(0, 1) * 255).round().numpy()
                for n in (1, 2)}
    assert np.abs(frame.astype(np.float64) - want[2]).max() <= 1
    assert np.abs(frame.astype(np.float64) - want[1]).max() > 5


def test_render_model_is_render_supersampled_with_the_models_n():
    prims = model(3)
    with torch.no_grad():
        assert torch.equal(render_model(prims, camera(), background=BG).color,
                           render_supersampled(prims, camera(), 3, background=BG).color)


# --- export -----------------------------------------------------------------------------------

def test_export_warns_in_one_line_for_one_ray_formats(tmp_path, cli):
    save_model(tmp_path / "two.safetensors", model(2))
    save_model(tmp_path / "one.safetensors", model(1))
    code, _, err = cli("export", tmp_path / "two.safetensors", "-f", "splat", "-o", tmp_path / "two.splat", "-q")
    assert code == 0 and (tmp_path / "two.splat").is_file(), err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("radfield: warning:") and "2x2" in lines[0], err
    code, _, err = cli("export", tmp_path / "one.safetensors", "-f", "splat", "-o", tmp_path / "one.splat", "-q")
    assert code == 0 and "warning" not in err, err
    assert supersample_warning(model(2), "points") is None  # a point cloud is not drawn per pixel
    assert supersample_warning(model(2), "ply-3dgs") is not None


def test_the_eval_stage_refuses_a_model_that_disagrees_with_its_run(tmp_path):
    """A run trained at n = 2 before model files recorded n: its eval stage must not measure it at 1."""
    from radfield.errors import RadfieldError
    from radfield.evaluation.evaluate import check_supersample

    save_model(tmp_path / "old.safetensors", model(1))
    save_model(tmp_path / "new.safetensors", model(2))
    check_supersample(tmp_path / "new.safetensors", 2)
    check_supersample(tmp_path / "old.safetensors", 1)
    with pytest.raises(RadfieldError, match="--force train") as error:
        check_supersample(tmp_path / "old.safetensors", 2)
    assert "\n" not in str(error.value)
