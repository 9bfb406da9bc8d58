"""Time-conditioned primitive kinds (core/kinds/dynamic.py, Splat the Net appendix C.1).

At a fixed time a dynamic model is the static model with phases b1 + ξ W_t and the DC S(ξ) (eq.
10-13), on every backend; the gradients of the temporal tensors against finite differences; a view
at a time outside [0, 1] is one error (one without a time: test_conditions.py); model files round-trip and refuse bad values; population control
keeps the new tensors' rows; and a tiny dynamic reconstruction fits what a static one cannot.
"""

import math
from dataclasses import replace

import pytest
import torch

from radfield.core import backends, kinds
from radfield.core.geometry.cameras import Camera, look_at
from radfield.core.kinds import DynamicNeuralPrimitives, Gaussians, NeuralPrimitives
from radfield.core.kinds.dynamic import TEMPORAL_TERMS
from radfield.core.render.rasterize import render
from radfield.core.render.reference import reference_render
from radfield.core.trainer.loop import make_strategy
from radfield.core.trainer.loop import (assemble, initial_state, load_checkpoint, make_optimizer, mean_psnr,
                                         save_checkpoint, train)
from radfield.model_file import load_model, save_model
from radfield.errors import RadfieldError

from shared_helpers import refine_everything, with_time

BG = (0.2, 0.3, 0.4)


def temporal_dc_offset(coeffs, xi, omega):
    """Eq. 10-12 written out: Σ a_i ξ^i + Σ (b_i cos(i ω ξ) + c_i sin(i ω ξ)), coeffs (P, 12, ...)."""
    a, b, c = coeffs[:, 0:4], coeffs[:, 4:8], coeffs[:, 8:12]
    out = torch.zeros_like(coeffs[:, 0])
    for i in range(1, 5):
        out = out + a[:, i - 1] * xi**i + b[:, i - 1] * math.cos(i * omega * xi) + c[:, i - 1] * math.sin(i * omega * xi)
    return out


def dynamic_views(size=16):
    """3 cameras × 3 moments of a random dynamic neural model, and the model."""
    from radfield.core.kinds import random_neural

    base = random_neural(12, scale=0.3, extent=0.45, b2=1.5, w2_amplitude=0.4, seed=3)
    truth = with_time(base, seed=5)
    truth.sh_t *= 3.0    # colours that change clearly over time
    cams = [Camera(fx=20.0, fy=20.0, cx=size / 2, cy=size / 2, width=size, height=size, conditions={"time": xi},
                   c2w=look_at((2.2 * math.cos(a), 2.2 * math.sin(a), 0.6), (0, 0, 0)), name=f"c{k}@{xi}")
            for k, a in enumerate((0.0, 2.1, 4.2)) for xi in (0.0, 0.5, 1.0)]
    with torch.no_grad():
        images = torch.stack([render(truth, c, background=(1.0, 1.0, 1.0)).color for c in cams])
    return base, cams, images


def scene(render_scene, kind, dtype=torch.float64):
    prims, cam = render_scene("neural-window" if kind == "neural-dynamic" else "gaussian", dtype)
    return with_time(prims), cam


def static_at(prims, xi):
    """The static model a dynamic one is at time ξ, built here from eq. 10-13."""
    sh = prims.sh.clone()
    sh[:, 0] = sh[:, 0] + temporal_dc_offset(prims.sh_t, xi, prims.time_frequency)
    if isinstance(prims, DynamicNeuralPrimitives):
        fields = {k: getattr(prims, k) for k in ("means", "log_scales", "quats", "w1", "w2", "b2")}
        return NeuralPrimitives(**fields, sh=sh, b1=prims.b1 + xi * prims.w_t, omega0=prims.omega0, window=prims.window)
    opacities = prims.opacities + temporal_dc_offset(prims.opacity_t, xi, prims.time_frequency)
    return Gaussians(means=prims.means, log_scales=prims.log_scales, quats=prims.quats, sh=sh, opacities=opacities)


@pytest.mark.parametrize("kind", ["neural-dynamic", "gaussian-dynamic"])
def test_at_a_fixed_time_a_dynamic_model_renders_as_its_static_model(render_scene, kind):
    prims, cam = scene(render_scene, kind)
    assert kinds.of(prims).name == kind and kinds.of(prims).conditions == ("time",)
    images = []
    for backend in backends.available("cpu", torch.float64):
        with backends.using(backend):
            for xi in (0.0, 0.37, 1.0):
                dynamic = render(prims, cam.at(time=xi), background=BG, near=0.05)
                static = render(static_at(prims, xi), cam, background=BG, near=0.05)
                assert static.meta["contributing_pairs"] > 100 and dynamic.meta == static.meta
                torch.testing.assert_close(dynamic.color, static.color, rtol=0, atol=1e-12)
                torch.testing.assert_close(dynamic.alpha, static.alpha, rtol=0, atol=1e-12)
                torch.testing.assert_close(dynamic.depth, static.depth, rtol=0, atol=1e-12)
                images.append(dynamic.color)
    # time matters: the moments differ
    assert (images[0] - images[1]).abs().max() > 0.05 and (images[1] - images[2]).abs().max() > 0.05


@pytest.mark.parametrize("kind,names", [("neural-dynamic", ("sh", "sh_t", "b1", "w_t")),
                                        ("gaussian-dynamic", ("sh", "sh_t", "opacities", "opacity_t"))])
def test_a_moment_and_its_gradients_are_eq_10_13_written_out(render_scene, kind, names):
    """at_time's one-product forms (kinds/dynamic.py: the cost of time) against static_at, in float32."""
    prims, _ = scene(render_scene, kind, torch.float32)
    for xi in (0.0, 0.37, 1.0):
        results = []
        for moment in (kinds.get(kind).at_time, static_at):
            leaves = {n: getattr(prims, n).detach().clone().requires_grad_(True) for n in names}
            m = moment(replace(prims, **leaves), xi)
            outputs = [m.sh, m.b1 if kind == "neural-dynamic" else m.opacities]
            weights = [torch.randn(o.shape, generator=torch.Generator().manual_seed(k)) for k, o in enumerate(outputs)]
            sum((o * w).sum() for o, w in zip(outputs, weights)).backward()
            results.append(([o.detach() for o in outputs], {n: t.grad for n, t in leaves.items()}))
        (fast, fast_grads), (slow, slow_grads) = results
        for a, b in zip(fast, slow):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
        for n in names:
            assert slow_grads[n].abs().max() > 0 or (xi == 0.0 and n == "w_t"), n   # ∂b1/∂W_t = ξ
            torch.testing.assert_close(fast_grads[n], slow_grads[n], rtol=1e-5, atol=1e-5, msg=n)


def test_the_slow_reference_draws_a_dynamic_model_at_the_views_time(render_scene):
    prims, cam = scene(render_scene, "gaussian-dynamic")
    small = cam.scaled(0.5).at(time=0.6)
    slow = reference_render(prims, small, background=BG, near=0.05)
    assert (render(prims, small, background=BG, near=0.05).color - slow).abs().max() < 1e-6


@pytest.mark.parametrize("kind,name", [("neural-dynamic", "w_t"), ("neural-dynamic", "sh_t"), ("neural-dynamic", "b1"),
                                       ("gaussian-dynamic", "sh_t"), ("gaussian-dynamic", "opacity_t")])
def test_gradients_of_the_temporal_tensors_match_finite_differences(render_scene, kind, name):
    prims, cam = scene(render_scene, kind)
    prims = prims.select(slice(3, 8))   # in front of the camera, a handful
    cam = Camera(fx=cam.fx / 3, fy=cam.fy / 3, cx=3.6, cy=3.1, width=7, height=6, c2w=cam.c2w).at(time=0.63)
    for backend in backends.available("cpu", torch.float64):
        with backends.using(backend):
            def f(x):
                out = render(replace(prims, **{name: x}), cam, background=BG, near=0.05)
                return torch.cat([out.color.flatten(), out.alpha.flatten(), out.depth.flatten() * 0.1])

            x = getattr(prims, name).clone().requires_grad_(True)
            assert float(f(x).detach()[-42:].abs().sum()) > 0    # something is drawn
            assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-5, rtol=1e-3), backend


def test_a_view_at_a_time_outside_0_1_is_one_error(render_scene):
    # (a view without a time, and the kinds that ignore one: test_conditions.py)
    for kind in ("neural-dynamic", "gaussian-dynamic"):
        prims, cam = scene(render_scene, kind)
        with pytest.raises(RadfieldError, match=r"^time 1.5 of view .* is outside \[0, 1\]"):
            render(prims, cam.at(time=1.5))


@pytest.mark.parametrize("kind", ["neural-dynamic", "gaussian-dynamic"])
def test_model_files_round_trip_and_refuse_bad_values(render_scene, kind, tmp_path):
    prims, cam = scene(render_scene, kind, torch.float32)
    path = tmp_path / "dynamic.safetensors"
    save_model(path, prims)
    loaded = load_model(path)
    assert type(loaded) is type(prims) and loaded.time_frequency == pytest.approx(2 * math.pi)
    for name, t in prims.tensors().items():
        assert torch.equal(getattr(loaded, name), t), name
    moment = cam.at(time=0.25)
    assert torch.equal(render(loaded, moment).color, render(prims, moment).color)

    with pytest.raises(RadfieldError, match=r"metadata 'time_frequency' must be a positive number"):
        save_model(tmp_path / "bad.safetensors", prims, extra={"time_frequency": "-1.0"})
        load_model(tmp_path / "bad.safetensors")
    wild = prims.map(lambda t: t.clone())
    wild.sh_t[3, 5, 1] = 1e6
    save_model(tmp_path / "wild.safetensors", wild)
    with pytest.raises(RadfieldError, match=r"wild.safetensors: tensor 'sh_t' is out of range at primitive 3"):
        load_model(tmp_path / "wild.safetensors")
    short = prims.map(lambda t: t[:, :5] if t.shape[-1] == TEMPORAL_TERMS or t.ndim == 3 and t.shape[1] == 12 else t)
    save_model(tmp_path / "short.safetensors", short)
    with pytest.raises(RadfieldError, match=r"short.safetensors: tensor '(sh_t|opacity_t)' has shape"):
        load_model(tmp_path / "short.safetensors")


@pytest.mark.parametrize("kind", ["neural-dynamic", "gaussian-dynamic"])
def test_population_control_carries_the_temporal_tensors(render_scene, densify_config, kind):
    prims, cam = scene(render_scene, kind, torch.float32)
    params, before, report = refine_everything(prims, kind, densify_config())
    grown = len(params["means"])
    for name, t in params.items():
        assert t.shape[0] == grown, name
    # the new rows are their parents' temporal tensors (clone: exact copy; split: the same MLP and colour)
    for name in ("w_t", "sh_t", "opacity_t"):
        if name in params:
            rows = {tuple(r.flatten().tolist()) for r in before[name]}
            assert all(tuple(r.flatten().tolist()) in rows for r in params[name].detach()), name
    grown_prims = assemble(params, kind, kinds.get(kind).attrs(prims))
    assert render(grown_prims, cam.at(time=0.5)).meta["visible"] > 0


def peak_opacity(params, prims, times):
    """sigmoid of the opacity logit of eq. 10-12 written out, its largest over `times` (P,)."""
    kind = kinds.get("gaussian-dynamic")
    moments = [kind.at_time(assemble(params, "gaussian-dynamic", kind.attrs(prims)), xi) for xi in times]
    return torch.stack([torch.sigmoid(m.opacities.detach()) for m in moments]).amax(0)


def gaussian_strategy_state(prims, densify):
    params = {n: t.clone().requires_grad_(True) for n, t in initial_state(prims, 1).params.items()}
    optimizer = make_optimizer(params, {k: 1e-3 for k in ("means", "log_scales", "quats", "sh_dc", "sh_rest",
                                                          "opacities")}, 1.0, "gaussian-dynamic")
    strategy = make_strategy("gaussian-dynamic", densify, extent=1.0, near=0.05, max_primitives=None,
                             initial_count=len(prims), attrs=kinds.get("gaussian-dynamic").attrs(prims))
    return params, optimizer, strategy, strategy.init_state(len(prims), "cpu")


def test_the_gaussian_reset_sets_the_opacity_peak_over_time_to_the_reset_value(render_scene, densify_config):
    prims, _ = scene(render_scene, "gaussian-dynamic", torch.float32)
    # large temporal swings that cancel in part, as trained models have
    prims = replace(prims, opacity_t=prims.opacity_t * torch.tensor([20.0] * 4 + [1.0] * (len(prims) - 4))[:, None])
    densify = densify_config()
    densify["gaussian"]["opacity_reset_every"] = 10
    params, optimizer, strategy, acc = gaussian_strategy_state(prims, densify)
    before = peak_opacity(params, prims, [k / 400 for k in range(401)])
    report = strategy.refine(acc, params, optimizer, 10, torch.Generator().manual_seed(0))
    assert report.get("opacity_reset") == 1
    peak = peak_opacity(params, prims, [k / 50 for k in range(51)])
    assert float(peak.max()) <= 0.01 + 1e-6
    # not below it: each Gaussian that was above 0.01 peaks at 0.01 (3DGS's reset value), so it can
    # grow back where a view needs it; between the strategy's 101 moments these ×20 swings (ω = 2π)
    # overshoot it a little
    fine = peak_opacity(params, prims, [k / 400 for k in range(401)])
    above = before > 0.0101
    assert int(above.sum()) >= 4 and float(fine[above].min()) > 0.0099 and float(fine.max()) < 0.012
    assert not torch.equal(params["opacity_t"].detach(), torch.zeros_like(params["opacity_t"]))   # shape kept


def test_the_gaussians_pruned_are_those_transparent_at_every_moment(render_scene, densify_config):
    prims, _ = scene(render_scene, "gaussian-dynamic", torch.float32)
    n = len(prims)
    # Gaussian 0: opaque at ξ = 1 only (its ξ⁴ term), transparent before; Gaussian 1: transparent at
    # every moment although its coefficients are large (ω = 1: −38 + 30 cos ξ + 15 ξ² − 1.25 ξ⁴ =
    # −8 + 30 (cos ξ − 1 + ξ²/2 − ξ⁴/24) ≈ −8 on [0, 1], where the closed-form bound
    # o + Σ max(a_i, 0) + Σ √(b_i² + c_i²) = 7 calls it opaque); the others opaque at every moment
    opacities, opacity_t = torch.full((n,), 3.0), torch.zeros(n, TEMPORAL_TERMS)
    opacities[0], opacity_t[0, 3] = -12.0, 15.0
    opacities[1], opacity_t[1, [4, 1, 3]] = -38.0, torch.tensor([30.0, 15.0, -1.25])
    prims = replace(prims, opacities=opacities, opacity_t=opacity_t, time_frequency=1.0)
    densify = densify_config()
    params, optimizer, strategy, acc = gaussian_strategy_state(prims, densify)
    times = [k / 400 for k in range(401)]
    peak = peak_opacity(params, prims, times)
    assert float(peak[0]) > 0.9 and float(peak[1]) < 0.001
    report = strategy.refine(acc, params, optimizer, densify["every"], torch.Generator().manual_seed(0))
    assert report["pruned"] == 1 and len(params["means"]) == n - 1
    assert torch.equal(params["opacity_t"][0].detach(), prims.opacity_t[0])   # the moment-only Gaussian stays


def test_a_tiny_dynamic_reconstruction_beats_the_same_budget_trained_as_static(cfg, tmp_path):
    """3 cameras × 3 moments, 16×16, of a random dynamic neural model; the dynamic kind and the static
    one start from the same primitives (the truth's geometry, its temporal terms and colours reset)."""
    base, cams, images = dynamic_views()
    start_static = replace(base, sh=torch.zeros_like(base.sh))
    start_dynamic = kinds.get("neural-dynamic").from_points(
        {k: getattr(start_static, k) for k in ("means", "log_scales", "quats", "sh")},
        {"hidden": base.hidden, "omega0": base.omega0, "time_frequency": 2 * math.pi}, seed=0)
    start_dynamic = replace(start_dynamic, w1=base.w1, b1=base.b1, w2=base.w2, b2=base.b2)
    train_cfg = cfg("train", iterations=150, sh_degree=0, batch_views=3, checkpoint_every=1000, eval_every=0)
    train_cfg["lr"] = {k: v * 10 for k, v in train_cfg["lr"].items()}    # a short run: larger steps
    scores = {}
    for name, start in (("static", start_static), ("dynamic", start_dynamic)):
        state = train(start, cams, images, train_cfg, background=(1.0, 1.0, 1.0), extent=1.0, seed=0)
        trained = state.primitives()
        assert len(trained) == 12 and kinds.of(trained).name == ("neural" if name == "static" else "neural-dynamic")
        scores[name] = mean_psnr(trained, cams, images, background=(1.0, 1.0, 1.0))
        if name == "dynamic":
            assert float(trained.w_t.abs().max()) > 0 and float(trained.sh_t.abs().max()) > 0
            save_checkpoint(tmp_path / "state.safetensors", state)
            back = load_checkpoint(tmp_path / "state.safetensors")
            assert back.kind == "neural-dynamic" and back.attrs["time_frequency"] == pytest.approx(2 * math.pi)
            assert torch.equal(back.params["w_t"], state.params["w_t"])
    assert scores["dynamic"] > scores["static"] + 3.0, scores


@pytest.mark.parametrize("kind", ["neural-dynamic", "gaussian-dynamic"])
def test_a_killed_dynamic_run_resumes_to_the_uninterrupted_model(cfg, tmp_path, kind, kill_and_resume):
    from radfield.core.kinds import random_gaussians

    _, cams, images = dynamic_views()
    if kind == "neural-dynamic":
        start = with_time(kinds.get("neural").from_points(
            {k: getattr(random_gaussians(30, sh_degree=1, extent=0.5, scale=0.12, seed=3), k)
             for k in ("means", "log_scales", "quats", "sh")}, {}, seed=1), seed=2)
    else:
        start = with_time(random_gaussians(30, sh_degree=1, extent=0.5, scale=0.12, seed=3), seed=2)
    train_cfg = cfg("train", iterations=12, sh_degree=1, sh_increase_every=6, batch_views=2, checkpoint_every=5)
    train_cfg["densify"] = {**train_cfg["densify"], "start": 4, "stop": 8, "every": 4}
    train_cfg["densify"]["gaussian"] = {**train_cfg["densify"]["gaussian"], "opacity_reset_every": 8}
    run = dict(background=(1.0, 1.0, 1.0), extent=2.0, seed=7)
    whole = train(start, cams, images, train_cfg, **run)
    saved, resumed = kill_and_resume(start, cams, images, train_cfg, tmp_path / "state.safetensors", kill_at=7, **run)
    assert saved.step == 5 and resumed.step == whole.step == 12
    assert resumed.attrs["time_frequency"] == whole.attrs["time_frequency"] == pytest.approx(2 * math.pi)
    assert len(whole.params["means"]) != 30   # population control acted
    for name in whole.params:
        assert torch.equal(whole.params[name], resumed.params[name]), name


def test_edits_commute_with_time(render_scene):
    """A cage map, a halving and joining with a model of another ω0 and MLP width, applied to the
    dynamic model and then taken at ξ, equal the same edit of the static model at ξ."""
    import numpy as np

    from radfield.edit.affine import deform_field, split_primitives
    from radfield.edit.field import Field, box_cage

    prims, _ = scene(render_scene, "neural-dynamic", torch.float64)
    kind = kinds.get("neural-dynamic")
    vertices, tets = box_cage([-4, -4, -4], [4, 4, 4], 2)
    stretch = np.array([1.5, 0.8, 1.1])

    def deformed(p):
        fld = Field(p, vertices, tets)
        fld.rebind()
        return deform_field(fld, vertices * stretch, split=None).prims

    halved = lambda p: split_primitives(p, np.array([1, 4, 6]))
    other = replace(prims.select(slice(0, 3)), omega0=20.0)
    other = replace(other, w1=other.w1[:, :5], b1=other.b1[:, :5], w2=other.w2[:, :5], w_t=other.w_t[:, :5])
    joined_b = lambda a, b: kinds.of(a).harmonise(a, b)[1]
    for xi in (0.0, 0.7):
        for edit in (deformed, halved):
            moment, static = kind.at_time(edit(prims), xi), edit(kind.at_time(prims, xi))
            for name, t in static.tensors().items():
                torch.testing.assert_close(getattr(moment, name), t, msg=name)
        moment = kind.at_time(joined_b(prims, other), xi)
        static = joined_b(kind.at_time(prims, xi), kind.at_time(other, xi))
        assert moment.hidden == 8 and moment.omega0 == prims.omega0
        for name, t in static.tensors().items():
            torch.testing.assert_close(getattr(moment, name), t, msg=name)


def test_the_peak_density_is_the_largest_over_time(render_scene):
    for kind_name in ("neural-dynamic", "gaussian-dynamic"):
        prims, _ = scene(render_scene, kind_name, torch.float64)
        kind = kinds.get(kind_name)
        peak = kind.peak_density(prims, samples=32)
        static = kinds.get(kind_name.removesuffix("-dynamic"))
        at = [static.peak_density(kind.at_time(prims, xi), samples=32) for xi in (0.0, 0.25, 0.5, 0.75, 1.0)]
        assert peak.shape == (len(prims),) and (peak >= torch.stack(at).amax(0) - 1e-9).all()
        assert (peak > torch.stack(at).amin(0) + 1e-6).any()   # a moment with less density exists
