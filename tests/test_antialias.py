"""Anti-aliasing of training (radfield.core.render.antialias): sub-pixel ray jitter and the footprint floor."""

import json
import math

import pytest
import torch

from radfield.core.train.footprint import FootprintFloor
from radfield.core.render.antialias import jitter_offsets, render_supersampled, shifted
from radfield.core.geometry.cameras import Camera, look_at, pixel_rays
from radfield.model_file import load_model
from radfield.evaluation.metrics import psnr
from radfield.core.kinds import random_gaussians, random_neural
from radfield.core.render.rasterize import render
from radfield.core.trainer.loop import generator, load_checkpoint, mean_psnr, save_checkpoint, train
from radfield.datasets.images import read_image
from radfield.datasets.scene import load_scene
from radfield.demo.static import generate_scene

from radfield.pipeline.config import load_defaults

BG = (1.0, 1.0, 1.0)


def orbit(n: int, size: int, radius: float = 3.0) -> list[Camera]:
    return [Camera(fx=1.3 * size, fy=1.3 * size, cx=size / 2, cy=size / 2, width=size, height=size,
                   c2w=look_at((radius * math.cos(a), radius * math.sin(a), 0.3 + 0.8 * math.sin(3 * a)), (0, 0, 0)))
            for a in (2 * math.pi * i / n for i in range(n))]


def synthetic_views(n: int, size: int):
    """n views of a random neural scene drawn by our renderer (the trainer tests' kind of scene)."""
    cameras, truth = orbit(n, size), random_neural(60, extent=0.6, scale=0.25, seed=1)
    with torch.no_grad():
        return cameras, torch.stack([render(truth, c, background=BG).color.clamp(0, 1) for c in cameras])


def config(**changes) -> dict:
    """The default train section with small-run changes (densify: a dict of train.densify changes)."""
    cfg = load_defaults()["train"]
    return {**cfg, **changes, "densify": {**cfg["densify"], **changes.get("densify", {})}}


def test_jitter_offsets_are_seeded_uniform_and_off_at_zero():
    a = jitter_offsets(1.0, 4000, generator(0, 3, 5))
    assert a == jitter_offsets(1.0, 4000, generator(0, 3, 5))          # a function of (seed, step)
    assert a != jitter_offsets(1.0, 4000, generator(0, 3, 6))
    t = torch.tensor(a)
    assert t.abs().max() <= 0.5 and t.abs().max() > 0.49               # U(−1/2, 1/2)²
    assert t.mean(0).abs().max() < 0.02 and (t.var(0) - 1 / 12).abs().max() < 0.005
    assert (torch.tensor(jitter_offsets(0.4, 500, generator(1, 3, 0))).abs() <= 0.2).all()
    assert jitter_offsets(0.0, 3, generator(0, 3, 0)) == [(0.0, 0.0)] * 3


def test_a_shifted_camera_samples_the_pixels_at_the_offset():
    cam = orbit(1, 12)[0]
    moved = shifted(cam, (0.25, -0.4))
    assert shifted(cam, (0.0, 0.0)) is cam
    # pixel (i, j) of the moved camera looks along the ray through (j + 0.5 − 0.25, i + 0.5 + 0.4) of cam
    j, i = torch.meshgrid(torch.arange(12.0) + 0.25, torch.arange(12.0) + 0.9, indexing="xy")
    d = torch.stack([(j - cam.cx) / cam.fx, (i - cam.cy) / cam.fy, torch.ones_like(i)], -1).double()
    d = torch.nn.functional.normalize(d, dim=-1) @ cam.c2w[:3, :3].T
    assert torch.allclose(pixel_rays(moved, dtype=torch.float64)[0], d, atol=1e-12)


def supersample_offsets(n: int) -> list[tuple[float, float]]:
    """The sub-pixel offsets of eq. (3) of radfield.core.render.antialias: the n × n cell centres of a
    pixel, ((a + ½)/n − ½, (b + ½)/n − ½): the reference's shifted single-ray renders."""
    grid = [(a + 0.5) / n - 0.5 for a in range(n)]
    return [(dx, dy) for dy in grid for dx in grid]


def test_supersampling_is_the_mean_of_the_sub_pixel_renders():
    # neural primitives: a ray's α depends on the ray alone, so the large view's pixels are exactly the
    # shifted views' (Gaussians differ by design: their 0.3 px² EWA dilation is in sub-pixels there)
    cam = orbit(2, 12)[1]
    prims = random_neural(40, extent=0.6, scale=0.2, seed=5)
    prims = prims.map(lambda t: t.clone().requires_grad_(True))
    assert supersample_offsets(2) == [(-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)]
    for n in (2, 3):
        fast = render_supersampled(prims, cam, n, background=BG)
        outs = [render(prims, shifted(cam, o), background=BG) for o in supersample_offsets(n)]
        for field in ("color", "alpha", "depth"):
            slow = sum(getattr(o, field) for o in outs) / n**2
            assert getattr(fast, field).shape == slow.shape
            assert torch.allclose(getattr(fast, field), slow, atol=1e-5), (n, field)
        # the same gradients (weights of the pixels of a random loss)
        w = torch.rand(12, 12, 3, generator=torch.Generator().manual_seed(n))
        g_fast = torch.autograd.grad((fast.color * w).sum(), prims.means)[0]
        g_slow = torch.autograd.grad((sum(o.color for o in outs) / n**2 * w).sum(), prims.means)[0]
        # (float32 ray coordinates differ in the last bits between the two ways: pairs at the 1/255
        # skip threshold can flip, and ⅓ is inexact: the gradients agree to 1e-3 of their scale, not to rounding)
        assert torch.allclose(g_fast, g_slow, atol=1e-3 * g_slow.abs().max().item()), n
    assert torch.equal(render_supersampled(prims, cam, 1, background=BG).color, render(prims, cam, background=BG).color)


def test_training_with_supersampling_fits_area_averages():
    # views of a scene rendered with 3 × 3 rays per pixel: a model trained with 3 × 3 fits them
    # better, measured the way it is trained, than one trained on pixel centres
    truth = random_neural(60, extent=0.6, scale=0.08, seed=1)
    cameras = orbit(6, 16)
    with torch.no_grad():
        images = torch.stack([render_supersampled(truth, c, 3, background=BG).color.clamp(0, 1) for c in cameras])
    start = random_neural(60, extent=0.6, scale=0.08, seed=2)
    run = dict(background=BG, extent=3.3, seed=0)
    cfg = config(iterations=40, sh_degree=0, densify={"start": 1000, "stop": 1000})
    plain = train(start, cameras, images, cfg, **run).primitives()
    boxed = train(start, cameras, images, {**cfg, "supersample": 3}, **run).primitives()
    assert mean_psnr(boxed, cameras, images, background=BG, supersample=3) > \
        mean_psnr(plain, cameras, images, background=BG, supersample=1)


@pytest.mark.parametrize("kind", ["neural", "gaussian"])
def test_jittered_training_resumes_bit_for_bit(tmp_path, kind):
    cameras, images = synthetic_views(4, 16)
    start = (random_neural if kind == "neural" else random_gaussians)(30, sh_degree=1, extent=0.6, scale=0.15, seed=3)
    cfg = config(iterations=10, sh_degree=1, batch_views=2, checkpoint_every=5, ray_jitter=1.0, min_footprint=1.0,
                 supersample=2, densify={"start": 4, "stop": 8, "every": 4})
    run = dict(background=BG, extent=3.3, seed=7)
    path = tmp_path / "checkpoint.safetensors"   # checkpoint_every 5 of 10 steps: the state after step 5
    whole = train(start, cameras, images, cfg, **run, checkpoint=lambda state: save_checkpoint(path, state))
    plain = train(start, cameras, images, {**cfg, "ray_jitter": 0.0}, **run)
    assert not torch.equal(whole.params["means"], plain.params["means"])  # the jitter acted
    saved = load_checkpoint(path)
    assert saved.step == 5
    resumed = train(start, cameras, images, cfg, **run, start_state=saved)
    for name in whole.params:
        assert torch.equal(whole.params[name], resumed.params[name]), name


def finest_pixel(means, cameras, near=0.01):
    """The obvious loop: per primitive, the smallest z/f (scene units per pixel at its centre) over the
    views whose image holds the centre; inf where none does."""
    out = []
    for mean in means.tolist():
        best = math.inf
        for c in cameras:
            x, y, z = (c.w2c[:3, :3] @ torch.tensor(mean, dtype=torch.float64) + c.w2c[:3, 3]).tolist()
            if z > near and 0 < c.fx * x / z + c.cx < c.width and 0 < c.fy * y / z + c.cy < c.height:
                best = min(best, z / max(c.fx, c.fy))
        out.append(best)
    return torch.tensor(out)


def test_the_floor_raises_thin_axes_only_and_is_idempotent():
    cams = orbit(3, 20)
    prims = random_neural(50, extent=0.5, scale=0.4, seed=2)
    log_scales = prims.log_scales.clone()
    log_scales[:25, 0] -= 4.0                                    # some very thin axes
    log_scales[0] = math.log(1e-6)                               # sub-pixel in every direction
    means = prims.means.clone()
    means[1] = torch.tensor([0.0, 0.0, 60.0])                   # seen by no view: left alone
    params = {"means": means, "log_scales": log_scales.clone()}
    FootprintFloor(cams, pixels=1.5, near=0.01).apply(params, 0)
    after = params["log_scales"]
    pixel = finest_pixel(means, cams)
    assert math.isinf(pixel[1]) and torch.isfinite(pixel[[0] + list(range(2, 50))]).all()
    want = torch.where(torch.isfinite(pixel)[:, None], torch.maximum(log_scales, torch.log(1.5 * pixel)[:, None]),
                       log_scales)
    assert torch.allclose(after, want, atol=1e-4)
    assert torch.equal(after[1], log_scales[1])
    above = log_scales > torch.log(1.5 * pixel)[:, None] + 1e-3
    assert above.any() and (~above).any()
    assert torch.equal(after[above], log_scales[above])          # axes above the floor keep their bits
    once = after.clone()
    FootprintFloor(cams, pixels=1.5, near=0.01).apply(params, 0)  # recomputed from the raised scales
    assert torch.equal(params["log_scales"], once)
    with pytest.raises(ValueError):
        FootprintFloor(cams, pixels=-1.0, near=0.01)


def test_after_training_no_primitive_is_thinner_than_the_floor():
    cameras, images = synthetic_views(4, 16)
    start = random_neural(30, extent=0.6, scale=0.02, seed=3)      # starts below 1 px in every view
    cfg = config(iterations=8, sh_degree=0, min_footprint=1.5, densify={"start": 4, "stop": 4, "every": 4})
    trained = train(start, cameras, images, cfg, background=BG, extent=3.3, seed=0).primitives()
    pixel = finest_pixel(trained.means, cameras)
    seen = torch.isfinite(pixel)
    assert seen.sum() > 20
    assert (trained.scales[seen] >= 1.5 * pixel[seen, None] * (1 - 1e-4)).all()
    free = train(start, cameras, images, {**cfg, "min_footprint": 0.0}, background=BG, extent=3.3, seed=0).primitives()
    assert (free.scales < finest_pixel(free.means, cameras)[:, None]).any()


@pytest.mark.parametrize("key, value", [("train.ray_jitter", "1.5"), ("train.ray_jitter", "-0.1"),
                                        ("train.min_footprint", "-1"), ("train.min_footprint", "9"),
                                        ("render.supersample", "0"), ("render.supersample", "5")])
def test_bad_values_are_one_line_errors(tmp_path_factory, tmp_path, cli, key, value):
    data = generate_scene("blobs", tmp_path_factory.mktemp("data") / "blobs", n_train=4, n_test=1, size=16)
    code, _, err = cli("reconstruct", data, "-o", tmp_path / "run", "--set", f"{key}={value}")
    assert code == 1 and len(err.strip().splitlines()) == 1 and key in err, err
    assert not (tmp_path / "run").exists()


def test_a_supersampled_run_is_measured_and_rendered_as_it_was_trained(tmp_path_factory, tmp_path, cli):
    data = generate_scene("blobs", tmp_path_factory.mktemp("data") / "blobs", n_train=4, n_test=2, size=16)
    run = tmp_path / "run"
    code, _, err = cli("reconstruct", data, "-o", run, "-q", "--set", "train.iterations=30", "--set",
                       "render.supersample=2", "--set", "init.num_points=200")
    assert code == 0, err
    model = load_model(run / "train" / "model.safetensors")
    assert model.supersample == 2  # the file records n (tests/test_supersample_model.py)
    scene = load_scene(run / "data" / "scene.json")
    images, _ = scene.load_images("test")
    with torch.no_grad():
        drawn = {n: [render_supersampled(model, c, n, background=scene.background).color.clamp(0, 1)
                     for c in scene.cameras("test")] for n in (1, 2)}
    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    by_n = {n: [float(psnr(d, im)) for d, im in zip(drawn[n], images)] for n in (1, 2)}
    assert [v["psnr"] for v in metrics["per_view"]] == pytest.approx(by_n[2], abs=0.05)  # eval at n = 2
    assert by_n[1] != pytest.approx(by_n[2], abs=0.05)                                   # which differs from n = 1
    code, _, err = cli("render", run, "-o", tmp_path / "frames")
    assert code == 0, err
    for camera, image in zip(scene.cameras("test"), drawn[2]):
        png = read_image(tmp_path / "frames" / f"{camera.name}.png")[..., :3]          # in [0, 1]
        assert abs(png - image.numpy()).max() <= 1 / 255 + 1e-6
