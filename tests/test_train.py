"""Training: losses and metrics, population control, the loop, checkpoints and the train stage."""

import dataclasses
import json
import math
import shutil

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from radfield.core.geometry.cameras import Camera, look_at
from radfield.model_file import load_model, save_model
from radfield.core.train.losses import anisotropy, density_magnitude, dssim, frequency_magnitude, photometric, psnr
from radfield.evaluation.metrics import ssim
from radfield.core.kinds import quat_to_rotmat, random_gaussians, random_neural
from radfield.core.render.rasterize import render
from radfield.core.train.strategy import edit_rows, in_frustum, negligible_density
from radfield.core.trainer.loop import make_strategy
from radfield.core.trainer.loop import (
    TrainState,
    initial_state,
    load_checkpoint,
    make_optimizer,
    mean_psnr,
    regularisers,
    save_checkpoint,
    train,
    views_for_step,
)
from radfield.core.trainer.log import read_log
from radfield.datasets.images import write_image
from radfield.stages import train as train_stage
from radfield.pipeline.config import load_defaults, section
from radfield.datasets.scene import Normalization, load_scene
from radfield.stages.train import MODEL_FILE
from radfield.pipeline.runner import Context

BG = (1.0, 1.0, 1.0)


def orbit(n: int, size: int, radius: float = 3.0) -> list[Camera]:
    """n cameras around the origin at varying heights, looking at it."""
    cameras = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = (radius * math.cos(a), radius * math.sin(a), 0.3 + 0.8 * math.sin(3 * a))
        cameras.append(Camera(fx=1.3 * size, fy=1.3 * size, cx=size / 2, cy=size / 2, width=size, height=size,
                              c2w=look_at(eye, (0, 0, 0)), name=f"view{i}"))
    return cameras


def synthetic_views(n: int, size: int):
    """Cameras and images of a known random neural scene rendered by our own renderer."""
    truth = random_neural(60, extent=0.6, scale=0.25, seed=1)
    cameras = orbit(n, size)
    with torch.no_grad():
        images = torch.stack([render(truth, c, background=BG).color.clamp(0, 1) for c in cameras])
    return cameras, images


def config(**changes) -> dict:
    """The default train section with small-run changes (densify=dict(...) updates train.densify)."""
    cfg = load_defaults()["train"]
    cfg["densify"].update(changes.pop("densify", {}))
    cfg.update(changes)
    return cfg


# --- losses and metrics ----------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_ssim_matches_scikit_image(dtype):
    g = np.random.default_rng(0)
    noise = g.random((40, 37, 3))
    smooth = np.cumsum(np.cumsum(g.random((40, 37, 3)), 0), 1)
    smooth /= smooth.max()
    for a in (noise, smooth):
        b = np.clip(a + 0.1 * g.standard_normal(a.shape), 0, 1)
        expected = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                         data_range=1, channel_axis=-1)
        got = float(ssim(torch.tensor(a, dtype=dtype), torch.tensor(b, dtype=dtype)))
        assert abs(got - expected) < 1e-4
    assert float(ssim(torch.tensor(noise), torch.tensor(noise))) == pytest.approx(1.0)


def test_training_ssim_is_the_3dgs_zero_padded_one():
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(20, 24, 3, generator=g), torch.rand(20, 24, 3, generator=g)
    # 3DGS: a 2D 11×11 window conv with padding 5 over (C, H, W)
    x = torch.arange(11.0) - 5
    w1d = torch.exp(-x**2 / 4.5)
    w1d /= w1d.sum()
    window = (w1d[:, None] * w1d[None, :]).expand(3, 1, 11, 11)
    blur = lambda z: torch.nn.functional.conv2d(z.permute(2, 0, 1)[None], window, padding=5, groups=3)
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    expected = (((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))).mean()
    torch.testing.assert_close(dssim(a, b), 1 - expected)


def test_psnr_and_anisotropy_values():
    ref = torch.zeros(4, 4, 3)
    assert float(psnr(ref + 0.1, ref)) == pytest.approx(20.0)
    assert float(anisotropy(torch.zeros(5, 3))) == 0.0
    # scales (1, 1, 4): ratios (1, 1, 4), Bessel-corrected std √3
    assert float(anisotropy(torch.log(torch.tensor([[1.0, 1.0, 4.0]])))) == pytest.approx(math.sqrt(3))


def test_frequency_and_density_penalties():
    w1 = torch.tensor([[[1.0, 2.0, 0.0], [0.0, 0.0, 3.0]], [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])  # (2, 2, 3)
    assert float(frequency_magnitude(w1)) == pytest.approx((14 + 1) / 2)
    w2, b2 = torch.tensor([[1.0, -2.0], [0.5, 0.0]]), torch.tensor([-1.0, 0.5])
    assert float(density_magnitude(w2, b2)) == pytest.approx((4 + 1) / 2)
    prims = random_neural(10)
    params = {"w1": prims.w1, "w2": prims.w2, "b2": prims.b2, "log_scales": prims.log_scales}
    off = config(lambda_aniso=0.0)
    assert regularisers(params, off, "neural") is None
    both = regularisers(params, config(lambda_aniso=0.0, lambda_w1=0.5, lambda_density=2.0), "neural")
    assert float(both) == pytest.approx(0.5 * float(frequency_magnitude(prims.w1))
                                        + 2.0 * float(density_magnitude(prims.w2, prims.b2)), rel=1e-6)
    gaussian = {"log_scales": prims.log_scales, "opacities": torch.zeros(10)}  # neural-only terms skip Gaussians
    assert regularisers(gaussian, config(lambda_aniso=0.0, lambda_w1=0.5, lambda_density=2.0), "gaussian") is None


def test_random_background_recomposites_the_rgba_targets():
    """Nothing in view, so every render is the background itself. Transparent views composited on
    BG: over a random background the target is that background, so the loss is exactly 0 at
    every step; opaque views of one colour: the random background changes the loss every step."""
    cameras = orbit(3, 16)
    empty = random_neural(5, seed=3).map(lambda t: t.clone())
    empty.means.add_(torch.tensor([0.0, 0.0, 100.0]))  # far above every camera's view
    cfg = config(iterations=4, random_background=True, densify={"start": 100, "stop": 100})
    clear = torch.ones(3, 16, 16, 3) * torch.tensor(BG)

    def losses(images, alphas, cfg):
        log = []
        train(empty, cameras, images, cfg, background=BG, extent=3.3, seed=0, alphas=alphas,
              on_step=lambda s, i: log.append(i["loss"]))
        return log

    assert losses(clear, torch.zeros(3, 16, 16), cfg) == [0.0] * 4
    grey = torch.full((3, 16, 16, 3), 0.25)
    random_losses = losses(grey, torch.ones(3, 16, 16), cfg)
    fixed = losses(grey, torch.ones(3, 16, 16), {**cfg, "random_background": False})
    assert len(set(random_losses)) == 4 and len(set(fixed)) == 1 and fixed[0] > 0.1


@pytest.mark.parametrize("make", [random_neural, random_gaussians])
def test_loss_gradients_are_finite(make):
    prims = make(40, sh_degree=1, extent=0.6, scale=0.2).map(lambda t: t.requires_grad_())
    camera = orbit(1, 16)[0]
    target = torch.rand(16, 16, 3, generator=torch.Generator().manual_seed(0))
    out = render(prims, camera, background=BG)
    loss = photometric(out.color, target, 0.2) + 1e-3 * anisotropy(prims.log_scales)
    loss.backward()
    for name, t in prims.tensors().items():
        assert torch.isfinite(t.grad).all(), name
    assert prims.means.grad.abs().sum() > 0


# --- population control ----------------------------------------------------------------------

def live_optimizer(prims, extent=1.0):
    """Params and an Adam that has taken one step, with every moment row tagged by its row index."""
    params = {n: t.requires_grad_() for n, t in initial_state(prims, prims.sh_degree).params.items()}
    optimizer = make_optimizer(params, load_defaults()["train"]["lr"], extent, prims.kind)
    for p in params.values():
        p.grad = torch.zeros_like(p)
    optimizer.step()
    for p in params.values():
        rows = torch.arange(p.shape[0], dtype=p.dtype).reshape(-1, *[1] * (p.ndim - 1))
        optimizer.state[p]["exp_avg"][:] = rows + 1
    return params, optimizer


def check_aligned(params, optimizer):
    for group in optimizer.param_groups:
        p = group["params"][0]
        assert params[group["name"]] is p and p.is_leaf and p.requires_grad
        state = optimizer.state[p]
        assert state["exp_avg"].shape == p.shape == state["exp_avg_sq"].shape
    assert len({p.shape[0] for p in params.values()}) == 1


def neural_case():
    """Six primitives in front of a camera, each in one situation of the rules."""
    prims = random_neural(6, extent=0.0, scale=0.05)
    prims.means[:] = torch.tensor([[0.0, 0.0, float(i) * 0.1 - 0.25] for i in range(6)])
    prims.log_scales[:] = math.log(0.005)                  # small: clone (grow_scale 0.01 × extent 1)
    prims.log_scales[1] = torch.log(torch.tensor([0.1, 0.02, 0.03]))  # large: split
    prims.log_scales[5] = math.log(1.5)                    # larger than prune_scale 1.0 (× extent 1): prune
    prims.b2[4], prims.w2[4] = -1.0, 0.01                  # density ≤ 0 everywhere: prune
    state = {"grad": torch.tensor([1e-3, 2e-3, 0.0, 0.0, 0.0, 0.0]), "count": torch.tensor([2.0, 2, 2, 0, 2, 2])}
    return prims, state


def test_neural_refine_clones_splits_prunes_and_keeps_adam_rows():
    prims, state = neural_case()
    params, optimizer = live_optimizer(prims)
    strategy = make_strategy("neural", config(densify={"grad_threshold": 1e-4})["densify"], extent=1.0, near=0.01,
                             max_primitives=None, initial_count=6)
    report = strategy.refine(state, params, optimizer, step=500, generator=torch.Generator().manual_seed(0))
    # 0 cloned, 1 split (removed, two children), 2 (seen, zero gradient), 4 (no density), 5 (huge) pruned;
    # 3 was never visible: kept
    assert report == {"cloned": 1, "split": 1, "pruned": 3}
    check_aligned(params, optimizer)
    means = params["means"].detach()
    assert means.shape[0] == 2 + 1 + 2
    torch.testing.assert_close(means[:2], prims.means[[0, 3]])   # kept rows, in order
    torch.testing.assert_close(means[2], prims.means[0])          # the clone
    exp_avg = optimizer.state[params["means"]]["exp_avg"]
    assert exp_avg[:2, 0].tolist() == [1.0, 4.0] and not exp_avg[2:].any()  # kept moments, new rows zero
    # split children: inside the parent's ellipsoid, scales / 1.6, same MLP
    parent_scales = torch.exp(prims.log_scales[1])
    for child in (3, 4):
        offset = quat_to_rotmat(prims.quats[1:2])[0].T @ (means[child] - prims.means[1])  # parent's frame
        assert (offset / parent_scales).norm() <= 1.0
        torch.testing.assert_close(params["log_scales"][child].detach(), prims.log_scales[1] - math.log(1.6))
        torch.testing.assert_close(params["w1"][child].detach(), prims.w1[1])
    assert not state["grad"].any() and state["grad"].shape == (5,)  # accumulators restart
    optimizer.step()  # the edited optimiser still steps


def test_budget_grows_only_the_largest_gradients_and_is_never_exceeded():
    prims = random_neural(10, extent=0.3, scale=0.005)
    params, optimizer = live_optimizer(prims)
    densify = config(densify={"grad_threshold": 1e-5})["densify"]
    state = {"grad": torch.linspace(1e-4, 1e-3, 10), "count": torch.ones(10)}
    strategy = make_strategy("neural", densify, extent=1.0, near=0.01, max_primitives=13, initial_count=10)
    report = strategy.refine(state, params, optimizer, step=500, generator=torch.Generator())
    assert report["cloned"] == 3 and params["means"].shape[0] == 13
    torch.testing.assert_close(params["means"][10:].detach(), prims.means[[7, 8, 9]])
    state = {"grad": torch.full((13,), 1e-3), "count": torch.ones(13)}
    strategy.refine(state, params, optimizer, step=600, generator=torch.Generator())
    assert params["means"].shape[0] == 13
    check_aligned(params, optimizer)


def test_a_population_that_starts_at_the_budget_is_left_alone():
    prims, state = neural_case()
    params, optimizer = live_optimizer(prims)
    strategy = make_strategy("neural", config(densify={"grad_threshold": 1e-4})["densify"], extent=1.0, near=0.01, max_primitives=6,
                             initial_count=6)
    assert strategy.refine(state, params, optimizer, step=500, generator=torch.Generator()) == {}
    assert params["means"].shape[0] == 6


def test_neural_thresholds_follow_the_view_size():
    """Stated for 64×64 views; the signal falls as 1/√pixels, so 4× the pixels halves them.
    Gaussians' NDC threshold is left as configured."""
    densify = config(densify={"grad_threshold": 4e-4, "prune_threshold": 2e-6})["densify"]
    common = dict(extent=1.0, near=0.01, max_primitives=None, initial_count=6)
    stated = make_strategy("neural", densify, **common, pixels=64 * 64)
    finer = make_strategy("neural", densify, **common, pixels=128 * 128)
    assert (stated.grad_threshold, stated.prune_threshold) == (4e-4, 2e-6)
    assert make_strategy("neural", densify, **common).grad_threshold == 4e-4   # no view size: as configured
    assert finer.grad_threshold == pytest.approx(2e-4) and finer.prune_threshold == pytest.approx(1e-6)
    gaussian = make_strategy("gaussian", densify, **common, pixels=128 * 128)
    assert gaussian.grad_threshold == densify["gaussian"]["grad_threshold"]
    # the scaled thresholds act in refine: a primitive with signal 3e-4 grows at 128×128, not at 64×64
    prims, state = neural_case()
    state["grad"] = torch.tensor([3e-4, 0, 0, 0, 0, 0]) * 2
    params, optimizer = live_optimizer(prims)
    assert stated.refine({k: v.clone() for k, v in state.items()}, params, optimizer, step=500,
                         generator=torch.Generator())["cloned"] == 0
    params, optimizer = live_optimizer(prims)
    assert finer.refine(state, params, optimizer, step=500, generator=torch.Generator())["cloned"] == 1


def test_visibility_and_gradient_statistics():
    camera = Camera(fx=20.0, fy=20.0, cx=10.0, cy=10.0, width=20, height=20, c2w=torch.eye(4))
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, -2.0], [5.0, 0.0, 2.0], [1.4, 0.0, 2.0]])
    visible = in_frustum(means, torch.tensor([0.1, 0.1, 0.1, 0.5]), camera, near=0.01)
    assert visible.tolist() == [True, False, False, True]  # behind; outside; outside but its sphere reaches in
    prims = random_neural(4, scale=0.1)
    prims.means[:] = means
    params = initial_state(prims, 0).params
    grads = {n: torch.ones_like(params[n]) for n in ("w1", "b1", "w2", "b2")}
    strategy = make_strategy("neural", config()["densify"], extent=1.0, near=0.01, max_primitives=None,
                             initial_count=4)
    state = strategy.init_state(4, "cpu")
    strategy.accumulate(state, params, grads, camera, step=1)
    n = prims.hidden
    assert state["count"].tolist() == [1, 0, 0, 0]
    assert float(state["grad"][0]) == pytest.approx(math.sqrt(3 * n) + 2 * math.sqrt(n) + 1)
    assert negligible_density(torch.tensor([[0.1, -0.1]]), torch.tensor([-0.2])).item()
    assert not negligible_density(torch.tensor([[0.1, -0.1]]), torch.tensor([0.0])).item()


def test_gaussian_refine_and_opacity_reset():
    prims = random_gaussians(4, extent=0.0, scale=0.005)
    prims.means[:] = torch.tensor([[0.0, 0.0, 0.1 * i] for i in range(4)])
    prims.log_scales[1] = math.log(0.05)       # large: split
    prims.opacities[:] = 2.0
    prims.opacities[3] = -8.0                  # sigmoid < 0.005: prune
    params, optimizer = live_optimizer(prims)
    state = {"grad": torch.tensor([1e-3, 1e-3, 0.0, 0.0]), "count": torch.ones(4)}
    densify = config(densify={"gaussian": {**config()["densify"]["gaussian"], "opacity_reset_every": 500}})["densify"]
    strategy = make_strategy("gaussian", densify, extent=1.0, near=0.01, max_primitives=None, initial_count=4)
    report = strategy.refine(state, params, optimizer, step=500, generator=torch.Generator().manual_seed(0))
    assert report == {"cloned": 1, "split": 1, "pruned": 1, "opacity_reset": 1}
    check_aligned(params, optimizer)
    assert params["means"].shape[0] == 2 + 1 + 2
    assert torch.sigmoid(params["opacities"].detach()).max() <= 0.01 + 1e-6
    assert not optimizer.state[params["opacities"]]["exp_avg"].any()


def test_edit_rows_with_a_boolean_mask_and_new_rows():
    prims = random_gaussians(3)
    params, optimizer = live_optimizer(prims)
    new = {n: torch.full((1, *p.shape[1:]), 7.0) for n, p in params.items()}
    edit_rows(params, optimizer, torch.tensor([True, False, True]), new)
    check_aligned(params, optimizer)
    assert params["means"][:, 0].tolist() == [float(prims.means[0, 0]), float(prims.means[2, 0]), 7.0]
    assert optimizer.state[params["quats"]]["exp_avg"][:, 0].tolist() == [1.0, 3.0, 0.0]


# --- the loop ----------------------------------------------------------------------------------

def test_views_are_walked_in_a_fresh_order_every_epoch():
    order = [views_for_step(3, s, 1, 5)[0] for s in range(10)]
    assert sorted(order[:5]) == sorted(order[5:]) == list(range(5)) and order[:5] != order[5:]
    assert views_for_step(3, 2, 2, 5) == order[4:6]


def test_a_short_run_learns_the_scene():
    cameras, images = synthetic_views(8, 32)
    start = random_neural(100, extent=0.6, scale=0.2, seed=2, b2=0.3, w2_amplitude=0.02)
    start.sh.zero_()
    cfg = config(iterations=60, sh_degree=0, densify={"start": 30, "stop": 30, "every": 30})
    cfg["lr"] = {k: v * 10 for k, v in cfg["lr"].items()}  # a short run: a larger step
    before = mean_psnr(start, cameras, images, background=BG)
    log = []
    state = train(start, cameras, images, cfg, background=BG, extent=3.3, seed=0, on_step=lambda s, i: log.append(i))
    after = mean_psnr(state.primitives(), cameras, images, background=BG)
    assert after > before + 6, (before, after)  # about 15 -> 25 dB
    assert len(log) == 60 and any("split" in i or "cloned" in i for i in log)


@pytest.mark.parametrize("kind", ["neural", "neural-window", "gaussian"])
def test_resuming_from_a_checkpoint_equals_an_uninterrupted_run(tmp_path, kind, kill_and_resume):
    cameras, images = synthetic_views(4, 16)
    start = (random_gaussians if kind == "gaussian" else random_neural)(30, sh_degree=1, extent=0.6, scale=0.15, seed=3)
    if kind == "neural-window":   # the checkpoint carries the window: a resumed run that lost it would differ
        start = dataclasses.replace(start, window=True)
    cfg = config(iterations=12, sh_degree=1, sh_increase_every=6, batch_views=2, checkpoint_every=5,
                 densify={"start": 4, "stop": 8, "every": 4})
    cfg["densify"]["gaussian"]["opacity_reset_every"] = 8
    run = dict(background=BG, extent=3.3, seed=7)
    whole = train(start, cameras, images, cfg, **run)

    saved, resumed = kill_and_resume(start, cameras, images, cfg, tmp_path / "checkpoint.safetensors", kill_at=7, **run)
    assert saved.step == 5
    assert resumed.step == whole.step == 12
    window = lambda state: state.attrs.get("window", False)
    assert window(resumed) == window(whole) == getattr(resumed.primitives(), "window", False) == (kind == "neural-window")
    assert len(whole.params["means"]) != 30  # population control acted
    for name in whole.params:
        assert torch.equal(whole.params[name], resumed.params[name]), name
        for key in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(whole.moments[name][key], resumed.moments[name][key]), (name, key)


def test_checkpoint_round_trip(tmp_path):
    state = initial_state(random_neural(5, sh_degree=2), 3)
    state = TrainState(9, state.kind, {**state.attrs, "window": True}, state.params,
                       {"means": {"exp_avg": torch.ones(5, 3), "exp_avg_sq": torch.ones(5, 3), "step": torch.tensor(9.0)}},
                       {"grad": torch.arange(5.0), "count": torch.ones(5)})
    save_checkpoint(tmp_path / "c.safetensors", state)
    back = load_checkpoint(tmp_path / "c.safetensors")
    assert (back.step, back.kind, back.attrs) == (9, "neural", {"omega0": state.attrs["omega0"], "window": True})
    assert back.params["sh_rest"].shape == (5, 15, 3)
    for name in state.params:
        assert torch.equal(back.params[name], state.params[name])
    assert torch.equal(back.moments["means"]["step"], torch.tensor(9.0))
    assert torch.equal(back.strategy["grad"], torch.arange(5.0))


# --- the stage ---------------------------------------------------------------------------------

def test_normalisation_round_trip(tmp_path):
    world = random_neural(40, sh_degree=1, extent=0.6, scale=0.2, seed=4)
    world.means += torch.tensor([3.0, -2.0, 1.0])
    norm = Normalization(torch.tensor([2.5, -2.2, 0.9], dtype=torch.float64), 0.4)
    camera = orbit(1, 24, radius=3.0)[0]
    c2w = camera.c2w.clone()
    c2w[:3, 3] += torch.tensor([3.0, -2.0, 1.0], dtype=torch.float64)
    camera = dataclasses.replace(camera, c2w=c2w)
    normalised = train_stage.to_normalized(world, norm)
    save_model(tmp_path / "m.safetensors", train_stage.to_world(normalised, norm))
    saved = load_model(tmp_path / "m.safetensors")
    with torch.no_grad():
        expected = render(normalised, norm.camera(camera), background=BG, near=0.05 * norm.scale).color
        got = render(saved, camera, background=BG, near=0.05).color
    assert (expected < 0.9).any()  # the view sees the primitives
    # float32 rounding of the moved means, amplified by ω0 = 30 in the density's phase
    torch.testing.assert_close(got, expected, atol=5e-4, rtol=0)


def stage_context(tmp_path, name, iterations=10):
    """A train-stage Context over a tiny scene.json (data-stage contract) and init model."""
    data = tmp_path / "data"
    if not data.exists():
        data.mkdir()
        cameras, images = synthetic_views(4, 16)
        views = []
        for camera, image in zip(cameras, images):
            path = data / f"{camera.name}.png"
            write_image(path, image.numpy())
            views.append({"name": camera.name, "image": str(path), "fx": camera.fx, "fy": camera.fy,
                          "cx": camera.cx, "cy": camera.cy, "width": 16, "height": 16, "c2w": camera.c2w.tolist(),
                          "file_width": 16, "file_height": 16, "distortion": None})
        scene = {"version": 1, "format": "nerf_synthetic", "root": str(data), "posed": True, "downscale": 1,
                 "background": list(BG), "normalization": {"center": [0.1, 0.0, 0.0], "scale": 1 / 3.2},
                 "extent": 1.1 * 3.2, "splits": {"train": views, "test": views[:1]}}
        (data / "scene.json").write_text(json.dumps(scene))
        save_model(data / "init.safetensors", random_neural(20, extent=0.6, scale=0.2, seed=5))
    cfg = section(load_defaults(), train_stage.STAGE.config_keys)
    cfg["train"].update(iterations=iterations, checkpoint_every=5)
    cfg["train"]["densify"].update(start=4, stop=8, every=4)
    (tmp_path / name).mkdir()
    for sub in ("tmp", "work"):
        (tmp_path / name / sub).mkdir()
    return Context(name="train", run_dir=tmp_path, stage_dir=tmp_path / name / "out", tmp=tmp_path / name / "tmp",
                   work=tmp_path / name / "work", config=cfg,
                   inputs={"scene.json": data / "scene.json", "init.safetensors": data / "init.safetensors",
                           "cage.npz": None},
                   outputs={out: tmp_path / name / "tmp" / out for out in train_stage.STAGE.outputs},
                   log=lambda line: None, quiet=True,
                   device="cpu")


def test_stage_writes_the_model_and_resumes_after_a_kill(tmp_path, monkeypatch):
    whole = stage_context(tmp_path, "whole")
    figures = train_stage.run(whole)
    assert figures["iterations"] == 10 and figures["primitives"] > 0 and figures["seconds_per_iteration"] > 0
    assert figures["window"] is False   # the stage's initial model (random_neural) is hard-edged
    assert figures["params"] == load_model(whole.outputs[MODEL_FILE]).num_params()
    assert math.isfinite(figures["train_psnr"])

    killed = stage_context(tmp_path, "killed")
    update = train_stage._TrainProgress.update

    def kill_at_7(self, step, info):
        if step == 7:
            raise KeyboardInterrupt
        update(self, step, info)

    monkeypatch.setattr(train_stage._TrainProgress, "update", kill_at_7)
    with pytest.raises(KeyboardInterrupt):
        train_stage.run(killed)
    monkeypatch.undo()
    assert (killed.work / train_stage.CHECKPOINT).is_file()
    lines = []
    resumed = train_stage.run(dataclasses.replace(killed, log=lines.append))
    assert lines == ["resuming from the checkpoint at step 5"]
    assert resumed["iterations"] == 10
    expected, got = load_model(whole.outputs[MODEL_FILE]), load_model(killed.outputs[MODEL_FILE])
    for name, tensor in expected.tensors().items():
        assert torch.equal(getattr(got, name), tensor), name
    # the log of the resumed run reads as the uninterrupted run's (seconds aside)
    strip = lambda records: [{k: v for k, v in r.items() if k != "seconds"} for r in records]
    whole_log, killed_log = read_log(whole.outputs[train_stage.LOG]), read_log(killed.outputs[train_stage.LOG])
    assert [r["step"] for r in killed_log] == list(range(1, 11))
    assert strip(killed_log) == strip(whole_log)


def test_stage_logs_every_step_and_draws_the_curves(tmp_path):
    ctx = stage_context(tmp_path, "run")
    ctx.config["train"]["eval_every"] = 4
    figures = train_stage.run(ctx)
    log = read_log(ctx.outputs[train_stage.LOG])
    assert [r["step"] for r in log] == list(range(1, 11))
    assert all({"loss", "psnr", "primitives", "seconds"} <= set(r) for r in log)
    assert all(math.isfinite(r["loss"]) and r["primitives"] > 0 for r in log)
    assert [r["seconds"] for r in log] == sorted(r["seconds"] for r in log)
    # population control at the densification steps (densify start 4, stop 8, every 4)
    assert {r["step"] for r in log if "pruned" in r} == {4, 8}
    # held-out PSNR at the multiples of eval_every and at the last step, equal to measuring the model
    assert [r["step"] for r in log if "test_psnr" in r] == [4, 8, 10]
    scene = load_scene(ctx.inputs["scene.json"])
    model = load_model(ctx.outputs[MODEL_FILE])
    measured = mean_psnr(model, scene.test_cameras, scene.test_images(), background=BG,
                         near=ctx.config["render"]["near"])
    assert log[-1]["test_psnr"] == pytest.approx(measured, abs=0.05)
    assert figures["last_test_psnr"] == log[-1]["test_psnr"]
    png = ctx.outputs[train_stage.CURVES].read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 10_000


def _finish(ctx) -> None:
    """Publish a stage attempt's outputs where the next run of the stage finds them and clear its
    scratch, as the pipeline does after a success."""
    ctx.tmp.rename(ctx.stage_dir)
    shutil.rmtree(ctx.work)
    ctx.work.mkdir()


def test_raising_iterations_continues_from_the_final_state(tmp_path):
    first = stage_context(tmp_path, "run", iterations=10)
    train_stage.run(first)
    _finish(first)
    previous = load_checkpoint(first.stage_dir / train_stage.FINAL_STATE)
    assert previous.step == 10

    more = dataclasses.replace(first, tmp=tmp_path / "run" / "tmp2", outputs={
        name: tmp_path / "run" / "tmp2" / name for name in train_stage.STAGE.outputs})
    more.tmp.mkdir()
    more.config["train"]["iterations"] = 14
    lines = []
    figures = train_stage.run(dataclasses.replace(more, log=lines.append))
    assert lines == ["continuing the finished run from step 10"]
    assert figures["iterations"] == 14 and figures["continued_from"] == 10
    log = read_log(more.outputs[train_stage.LOG])
    assert [r["step"] for r in log] == list(range(1, 15))
    assert log[:10] == read_log(first.stage_dir / train_stage.LOG)
    # it is exactly the trainer continued from the saved state under the 14-step schedules
    scene = load_scene(first.inputs["scene.json"])
    norm = scene.normalization
    cfg = dict(more.config["train"])
    cameras = [norm.camera(c) for c in scene.train_cameras]
    init = train_stage.to_normalized(load_model(first.inputs["init.safetensors"]), norm)
    state = train(init, cameras, scene.train_images(), cfg, background=BG, extent=scene.extent * norm.scale,
                  seed=more.config["seed"], near=more.config["render"]["near"] * norm.scale, start_state=previous)
    expected = train_stage.to_world(state.primitives(), norm)
    got = load_model(more.outputs[MODEL_FILE])
    for name, tensor in expected.tensors().items():
        assert torch.equal(getattr(got, name), tensor.to(torch.float32)), name

    # anything else changed as well: a fresh start
    other = dataclasses.replace(more, tmp=tmp_path / "run" / "tmp3", outputs={
        name: tmp_path / "run" / "tmp3" / name for name in train_stage.STAGE.outputs})
    other.tmp.mkdir()
    other.config["train"]["iterations"] = 12
    other.config["train"]["lambda_dssim"] = 0.3
    lines = []
    figures = train_stage.run(dataclasses.replace(other, log=lines.append))
    assert lines == [] and figures["continued_from"] == 0
    assert [r["step"] for r in read_log(other.outputs[train_stage.LOG])] == list(range(1, 13))


def test_masked_losses_measure_only_the_valid_pixels():
    g = torch.Generator().manual_seed(3)
    ref = torch.rand(24, 30, 3, generator=g)
    img = (ref + 0.1 * torch.randn(24, 30, 3, generator=g)).clamp(0, 1)
    mask = torch.zeros(24, 30, dtype=torch.bool)
    mask[3:20, 4:27] = True
    garbage = torch.where(mask[..., None], img, torch.rand(24, 30, 3, generator=g))
    black = torch.where(mask[..., None], ref, torch.zeros(()))  # a photo with invalid black borders
    inner = (slice(3, 20), slice(4, 27))
    # PSNR and L1: over the valid pixels, whatever the invalid ones hold
    assert float(psnr(garbage, black, mask)) == pytest.approx(float(psnr(img[inner], ref[inner])), abs=1e-4)
    # SSIM "valid": the windows lying wholly on valid pixels, i.e. skimage on the valid rectangle
    expected = structural_similarity(img[inner].double().numpy(), ref[inner].double().numpy(), gaussian_weights=True,
                                     sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1)
    assert float(ssim(garbage.double(), black.double(), mask=mask)) == pytest.approx(expected, abs=1e-6)
    # an all-valid mask changes nothing
    full = torch.ones(24, 30, dtype=torch.bool)
    assert float(ssim(img, ref, mask=full)) == pytest.approx(float(ssim(img, ref)), abs=1e-6)
    assert float(photometric(img, ref, 0.2, full)) == pytest.approx(float(photometric(img, ref, 0.2)), abs=1e-6)
    # the training loss sends no gradient to an invalid pixel
    x = garbage.clone().requires_grad_(True)
    photometric(x, black, 0.2, mask).backward()
    assert x.grad[~mask].abs().max() == 0 and x.grad[mask].abs().max() > 0
    with pytest.raises(ValueError, match="no 11×11 window"):
        ssim(img, ref, mask=torch.zeros(24, 30, dtype=torch.bool))
