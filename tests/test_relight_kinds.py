"""Relightable primitive kinds (core/kinds/relight.py, Splat the Net appendix C.2).

Under one light a relightable model is the static model of its view's colours (c_dc + c_θ(d, d_l))·E
(eq. 14), on every backend; a zero network draws c_dc; the gradients of the network, c_dc, μ and q
against finite differences; model files round-trip and refuse bad values; population control keeps
the network's rows; a turned primitive turns its colour field; a tiny relighting reconstruction
fits what a light-blind one cannot; and the centre colour against quadrature of the exact
volume-rendering integral with colour varying along the ray. (A view without a light is one error,
and the other kinds ignore one: test_conditions.py.)
"""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from radfield.core import backends, kinds
from radfield.core.geometry.cameras import Camera, Light, look_at
from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.core.kinds import Gaussians, NeuralPrimitives, RelightNeuralPrimitives
from radfield.core.kinds.relight import network_count
from radfield.core.render.rasterize import render
from radfield.core.kinds.neural_density import primitive_density
from radfield.core.render.reference import reference_render
from radfield.core.splat.sh import C0, eval_sh
from radfield.core.trainer.loop import assemble, mean_psnr, train
from radfield.model_file import load_model, save_model
from radfield.errors import RadfieldError

from shared_helpers import refine_everything, with_network

BG = (0.2, 0.3, 0.4)
POINT = Light(position=(1.0, -2.5, 1.5), intensity=9.0)
SUN = Light(direction=(-0.3, 0.5, -1.0), intensity=1.0)
NETWORK = ("color_w1", "color_b1", "color_w2", "color_b2")


def scene(render_scene, kind, dtype=torch.float64):
    prims, cam = render_scene("neural-window" if kind == "neural-relight" else "gaussian", dtype)
    return with_network(prims), cam.at(light=POINT)


def colour_by_hand(prims, i, campos, light):
    """Eq. 14 for primitive i written out: (SH colour + W2 softplus(W1 [Rᵀd, Rᵀd_l] + b1) + b2) · E."""
    mu = prims.means[i]
    d = (mu - campos) / (mu - campos).norm()
    if light.position is not None:
        to_light = torch.tensor(light.position, dtype=mu.dtype) - mu
        d_l, irradiance = to_light / to_light.norm(), light.intensity / float(to_light @ to_light)
    else:
        d_l, irradiance = -torch.tensor(light.direction, dtype=mu.dtype), light.intensity
    rot = quat_to_rotmat(prims.quats[i][None])[0]
    x = torch.cat([rot.T @ d, rot.T @ d_l])
    hidden = torch.log1p(torch.exp(prims.color_w1[i] @ x + prims.color_b1[i]))
    network = prims.color_w2[i] @ hidden + prims.color_b2[i]
    static = eval_sh(prims.sh[i][None], d[None], prims.sh_degree)[0] + 0.5
    return (static + network) * irradiance


@pytest.mark.parametrize("kind", ["neural-relight", "gaussian-relight"])
def test_under_one_light_a_relight_model_renders_as_its_static_model(render_scene, kind):
    prims, cam = scene(render_scene, kind)
    spec = kinds.of(prims)
    assert spec.name == kind and spec.conditions == ("light",)
    images = {}
    for light in (POINT, SUN):
        lit = cam.at(light=light)
        static = spec.at_view(prims, lit)
        assert type(static) in (NeuralPrimitives, Gaussians) and static.sh_degree == 0
        campos = cam.c2w[:3, 3]
        for i in range(len(prims)):   # the DC is (c − 0.5)/C0 of eq. 14's colour
            torch.testing.assert_close(C0 * static.sh[i, 0] + 0.5, colour_by_hand(prims, i, campos, light),
                                       rtol=0, atol=1e-12)
        for backend in backends.available("cpu", torch.float64):
            with backends.using(backend):
                relit, drawn = render(prims, lit, background=BG, near=0.05), render(static, lit, background=BG, near=0.05)
                assert drawn.meta["contributing_pairs"] > 100 and relit.meta == drawn.meta
                for a, b in zip(relit[:3], drawn[:3]):
                    torch.testing.assert_close(a, b, rtol=0, atol=0)
                images[light, backend] = relit.color
    # the backends agree, and the light matters
    torch.testing.assert_close(images[POINT, "torch"], images[POINT, "fused-cpu"], rtol=0, atol=1e-10)
    assert (images[POINT, "torch"] - images[SUN, "torch"]).abs().max() > 0.05


@pytest.mark.parametrize("kind", ["neural-relight", "gaussian-relight"])
def test_a_zero_network_under_unit_irradiance_draws_exactly_c_dc(render_scene, kind):
    prims, cam = scene(render_scene, kind)
    zero = replace(prims, color_w2=torch.zeros_like(prims.color_w2), color_b2=torch.zeros_like(prims.color_b2))
    parent = NeuralPrimitives if kind == "neural-relight" else Gaussians
    static = parent(**{k: getattr(prims, k) for k in parent.__dataclass_fields__ if k != "supersample"})
    for backend in backends.available("cpu", torch.float64):
        with backends.using(backend):
            relit = render(zero, cam.at(light=SUN), background=BG, near=0.05)   # E = intensity = 1
            plain = render(static, cam, background=BG, near=0.05)
            torch.testing.assert_close(relit.color, plain.color, rtol=0, atol=1e-12)
            torch.testing.assert_close(relit.alpha, plain.alpha, rtol=0, atol=0)


@pytest.mark.parametrize("kind,name", [("neural-relight", n) for n in NETWORK + ("sh", "means", "quats")]
                         + [("gaussian-relight", n) for n in NETWORK])
def test_gradients_of_the_colour_field_match_finite_differences(render_scene, kind, name):
    prims, cam = scene(render_scene, kind)
    prims = prims.select(slice(3, 8))   # in front of the camera, a handful
    cam = Camera(fx=cam.fx / 3, fy=cam.fy / 3, cx=3.6, cy=3.1, width=7, height=6, c2w=cam.c2w).at(light=POINT)
    for backend in backends.available("cpu", torch.float64):
        with backends.using(backend):
            def f(x):
                out = render(replace(prims, **{name: x}), cam, background=BG, near=0.05)
                return torch.cat([out.color.flatten(), out.alpha.flatten()])

            x = getattr(prims, name).clone().requires_grad_(True)
            grad = torch.autograd.grad(f(x).sum(), x)[0]
            assert float(grad.abs().max()) > 1e-6      # the view depends on it
            assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-5, rtol=1e-3), backend


def test_at_light_is_the_static_model_of_one_light_for_every_view(render_scene):
    """at_light fits the colour over view directions by SH (what an export under a light writes):
    close to the exact per-view colour, and exportable as Gaussians."""
    prims, cam = scene(render_scene, "neural-relight")
    prims = replace(prims, color_w2=prims.color_w2 * 0.3)   # a smooth field, as SH degree 3 can hold
    spec = kinds.get("neural-relight")
    static = spec.at_light(prims, POINT)
    assert type(static) is NeuralPrimitives and static.sh_degree == 3
    exact, fitted = render(prims, cam, background=BG, near=0.05), render(static, cam, background=BG, near=0.05)
    assert (exact.color - fitted.color).abs().max() < 0.05
    assert len(kinds.of(static).to_gaussians(static)) == len(prims)


@pytest.mark.parametrize("kind", ["neural-relight", "gaussian-relight"])
def test_model_files_round_trip_and_refuse_bad_values(render_scene, kind, tmp_path):
    prims, cam = scene(render_scene, kind, torch.float32)
    path = tmp_path / "relight.safetensors"
    save_model(path, prims)
    loaded = load_model(path)
    assert type(loaded) is type(prims)
    for name, t in prims.tensors().items():
        assert torch.equal(getattr(loaded, name), t), name
    assert torch.equal(render(loaded, cam).color, render(prims, cam).color)

    wild = prims.map(lambda t: t.clone())
    wild.color_w2[4, 1, 2] = 1e6
    save_model(tmp_path / "wild.safetensors", wild)
    with pytest.raises(RadfieldError, match=r"wild.safetensors: tensor 'color_w2' is out of range at primitive 4 "
                                            r"\(a colour-network weight beyond"):
        load_model(tmp_path / "wild.safetensors")
    short = replace(prims, color_w2=prims.color_w2[:, :, :5])
    save_model(tmp_path / "short.safetensors", short)
    with pytest.raises(RadfieldError, match=r"short.safetensors: tensor 'color_w2' has shape \(\d+, 3, 5\), "
                                            rf"expected \(P, 3, {prims.color_w1.shape[1]}\)"):
        load_model(tmp_path / "short.safetensors")


def test_the_parameter_count_stays_within_twice_the_static_kind(render_scene):
    static = kinds.get("neural").from_points(
        {"means": torch.zeros(2, 3), "log_scales": torch.zeros(2, 3), "quats": torch.tensor([[1.0, 0, 0, 0]] * 2),
         "sh": torch.zeros(2, 16, 3)}, {}, seed=0)
    # as the init stage makes it: SH degree 0, eq. 14's constant colour (the kind's init_settings)
    relight = kinds.get("neural-relight").from_points(
        {**{k: getattr(static, k) for k in ("means", "log_scales", "quats")}, "sh": static.sh[:, :1]}, {}, seed=0)
    per_static, per_relight = static.num_params() // 2, relight.num_params() // 2
    assert (per_static, per_relight, network_count()) == (99, 177, 123)
    assert per_relight <= 2 * per_static
    # a new model draws its points' colours: the network's output is 0
    assert torch.equal(relight.color_w2, torch.zeros_like(relight.color_w2)) and float(relight.color_w1.abs().max()) > 0


@pytest.mark.parametrize("kind", ["neural-relight", "gaussian-relight"])
def test_population_control_carries_the_colour_network(render_scene, densify_config, kind):
    prims, cam = scene(render_scene, kind, torch.float32)
    params, before, report = refine_everything(prims, kind, densify_config())
    grown = len(params["means"])
    for name in NETWORK:   # clone and split children carry their parent's network
        assert params[name].shape[0] == grown
        rows = {tuple(r.flatten().tolist()) for r in before[name]}
        assert all(tuple(r.flatten().tolist()) in rows for r in params[name].detach()), name
    grown_prims = assemble(params, kind, kinds.get(kind).attrs(prims))
    assert render(grown_prims, cam).meta["visible"] > 0


def test_a_turned_model_turns_its_colour_field(render_scene):
    """The model, its camera and its light under one similarity (edit/compose.py) render the same
    image: the network reads d and d_l in each primitive's own frame, which turns with it."""
    from radfield.edit.compose import similarity

    angle = 0.9
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k
    shift = np.array([0.2, -0.1, 0.3])
    move = torch.eye(4, dtype=torch.float64)
    move[:3, :3], move[:3, 3] = torch.from_numpy(rot), torch.from_numpy(shift)
    for kind in ("neural-relight", "gaussian-relight"):
        prims, cam = scene(render_scene, kind)
        turned = similarity(prims, rot, shift, 1.0)
        for name in NETWORK:   # the network's own tensors are those of the original
            assert torch.equal(getattr(turned, name), getattr(prims, name))
        for light, moved in ((POINT, Light(position=tuple(rot @ np.array(POINT.position) + shift), intensity=9.0)),
                             (SUN, Light(direction=tuple(rot @ np.array(SUN.direction)), intensity=1.0))):
            before = render(prims, cam.at(light=light), background=BG, near=0.05)
            after = render(turned, replace(cam, c2w=move @ cam.c2w).at(light=moved), background=BG, near=0.05)
            assert before.meta["contributing_pairs"] > 100
            torch.testing.assert_close(after.color, before.color, rtol=0, atol=1e-9)
        # and without turning the frame the colours would differ: the network is not rotation-invariant
        unturned = replace(turned, quats=prims.quats)
        assert not torch.allclose(kinds.of(prims).at_view(unturned, replace(cam, c2w=move @ cam.c2w).at(light=moved)).sh,
                                  kinds.of(prims).at_view(turned, replace(cam, c2w=move @ cam.c2w).at(light=moved)).sh)


def relight_views(size=16):
    """2 cameras × 4 point lights, 16×16, of a random relightable neural model, and its static part."""
    from radfield.core.kinds import random_neural

    base = random_neural(12, scale=0.3, extent=0.45, b2=1.5, w2_amplitude=0.4, seed=3)
    truth = with_network(base, seed=5, amplitude=0.3)   # colours within about [0, 1.8]
    lights = [Light(position=(2.5 * math.cos(a), 2.5 * math.sin(a), 1.5), intensity=8.5) for a in (0.3, 1.9, 3.5, 5.1)]
    cams = [Camera(fx=20.0, fy=20.0, cx=size / 2, cy=size / 2, width=size, height=size, conditions={"light": light},
                   c2w=look_at((2.2 * math.cos(a), 2.2 * math.sin(a), 0.6), (0, 0, 0)), name=f"c{k}/l{j}")
            for k, a in enumerate((0.0, 2.1)) for j, light in enumerate(lights)]
    with torch.no_grad():
        images = torch.stack([render(truth, c, background=(1.0, 1.0, 1.0)).color for c in cams])
    return base, cams, images


def test_a_tiny_relighting_reconstruction_beats_the_same_budget_trained_light_blind(cfg):
    """Both start from the truth's geometry and density with colours reset: the static neural kind
    (one SH colour per view direction) cannot follow the lights, the relightable kind can."""
    base, cams, images = relight_views()
    start_static = replace(base, sh=torch.zeros_like(base.sh))
    start_relight = kinds.get("neural-relight").from_points(
        {k: getattr(start_static, k) for k in ("means", "log_scales", "quats", "sh")},
        {"hidden": base.hidden, "omega0": base.omega0}, seed=0)
    start_relight = replace(start_relight, w1=base.w1, b1=base.b1, w2=base.w2, b2=base.b2)
    train_cfg = cfg("train", iterations=150, sh_degree=1, sh_increase_every=10, batch_views=4, checkpoint_every=1000,
                    eval_every=0)
    train_cfg["lr"] = {k: v * 10 for k, v in train_cfg["lr"].items()}    # a short run: larger steps
    train_cfg["lr"]["color"] = train_cfg["lr"]["mlp"]   # ... but 3× that for the network overshoots in 150 steps
    scores = {}
    for name, start in (("static", start_static), ("relight", start_relight)):
        trained = train(start, cams, images, train_cfg, background=(1.0, 1.0, 1.0), extent=1.0, seed=0).primitives()
        assert len(trained) == 12 and kinds.of(trained).name == ("neural" if name == "static" else "neural-relight")
        scores[name] = mean_psnr(trained, cams, images, background=(1.0, 1.0, 1.0))
    print("relight vs light-blind PSNR on the training views:", scores)
    assert scores["relight"] > scores["static"] + 3.0, scores   # measured: 22.6 dB against 17.6


def quadrature_image(prims, static, cam, colour_along_ray, background, samples=3000):
    """The exact volume-rendering integral C = ∫ T(ℓ) Σ_i σ_i(x)/max(s_i) c_i(x) dℓ + T(∞)·bg per
    pixel (midpoint rule over the span of the primitives), c_i(x) = the centre colour (the renderer's,
    from `static`) + colour_along_ray(i, x̂), x̂ = Rᵀ(x − μ)/max(s) in the primitive's own frame."""
    c2w, campos = cam.c2w, cam.c2w[:3, 3]
    centre = C0 * static.sh[:, 0] + 0.5
    rot = quat_to_rotmat(prims.quats)
    smax = prims.scales.amax(-1)
    dist = (prims.means - campos).norm(dim=-1)
    lo, hi = float((dist - 1.2 * smax).min()), float((dist + 1.2 * smax).max())
    step = (hi - lo) / samples
    ell = lo + (torch.arange(samples, dtype=torch.float64) + 0.5) * step
    image = torch.zeros(cam.height, cam.width, 3, dtype=torch.float64)
    for row in range(cam.height):
        for col in range(cam.width):
            d_cam = torch.tensor([(col + 0.5 - cam.cx) / cam.fx, (row + 0.5 - cam.cy) / cam.fy, 1.0], dtype=torch.float64)
            d = c2w[:3, :3] @ (d_cam / d_cam.norm())
            x = campos + ell[:, None] * d                                                # (S, 3)
            extinction, emitted = torch.zeros(samples, dtype=torch.float64), torch.zeros(samples, 3, dtype=torch.float64)
            for i in range(len(prims)):
                sigma = primitive_density(prims, i, x) / smax[i]
                own = ((x - prims.means[i]) @ rot[i]) / smax[i]
                extinction += sigma
                emitted += sigma[:, None] * (centre[i] + colour_along_ray(i, own))
            optical = torch.cumsum(extinction, 0) * step - 0.5 * extinction * step   # ∫ up to each midpoint
            transmittance = torch.exp(-optical)
            image[row, col] = (transmittance[:, None] * emitted).sum(0) * step \
                + math.exp(-float(extinction.sum() * step)) * torch.tensor(background, dtype=torch.float64)
    return image


def test_the_centre_colour_against_quadrature_of_a_colour_varying_along_the_ray():
    """The relight kinds take x at the centre (x̂ = 0): against the exact integral with a colour
    that varies linearly inside each primitive by ±0.1 per channel along a direction of its own frame,
    c(x̂) = c(0) + 0.1 a·x̂, |a| = 1. Three windowed primitives apart (no overlap on any ray)."""
    from radfield.core.kinds import random_neural

    base = random_neural(3, scale=0.25, extent=0.1, b2=3.0, w2_amplitude=0.3, seed=11, dtype=torch.float64)
    base.means = torch.tensor([[-0.55, 0.0, 0.1], [0.0, 0.1, -0.05], [0.55, -0.1, 0.0]], dtype=torch.float64)
    base.window = True
    prims = with_network(base, seed=2)
    cam = Camera(fx=14.0, fy=14.0, cx=8.0, cy=6.0, width=16, height=12, c2w=look_at((0.2, -2.6, 0.4), (0, 0, 0)),
                 conditions={"light": POINT})
    static = kinds.of(prims).at_view(prims, cam)
    drawn = render(prims, cam, background=BG, near=0.05).color
    a = torch.nn.functional.normalize(torch.randn(3, 3, 3, generator=torch.Generator().manual_seed(0),
                                                  dtype=torch.float64), dim=-1)   # (primitive, channel, 3)
    constant = quadrature_image(prims, static, cam, lambda i, own: torch.zeros(len(own), 3, dtype=torch.float64), BG)
    varying = quadrature_image(prims, static, cam, lambda i, own: 0.1 * own @ a[i].T, BG)
    alpha = render(prims, cam, background=BG, near=0.05).alpha
    covered = alpha > 0.05
    err_constant = float((drawn - constant).abs().max())
    err_varying = float((drawn - varying).abs().max())
    mean_varying = float((drawn - varying).abs()[covered].mean())
    print(f"centre colour vs exact integral: max |Δ| {err_varying:.4f}, mean over covered pixels {mean_varying:.4f} "
          f"(the same with a constant colour: {err_constant:.2e}; colour range inside a primitive ±0.1)")
    assert err_constant < 2e-3          # the renderer is the exact integral when the colour is constant
    assert 1e-3 < err_varying < 0.1     # the colour's variation along the ray shows, within its ±0.1 range


def test_cage_edits_and_halving_keep_each_primitives_network(render_scene):
    """A cage map and a halving (edit/affine.py) change the geometry and the density MLP as the
    parent kind's hooks do; the colour network, in the primitive's own frame, rides along."""
    from radfield.edit.affine import deform_field, split_primitives
    from radfield.edit.field import Field, box_cage

    prims, cam = scene(render_scene, "neural-relight")
    vertices, tets = box_cage([-4, -4, -4], [4, 4, 4], 2)
    fld = Field(prims, vertices, tets)
    fld.rebind()
    deformed = deform_field(fld, vertices * np.array([1.5, 0.8, 1.1]), split=None).prims
    assert type(deformed) is RelightNeuralPrimitives and not torch.equal(deformed.means, prims.means)
    halved = split_primitives(prims, np.array([1, 4, 6]))
    assert type(halved) is RelightNeuralPrimitives and len(halved) == len(prims) + 3
    for name in NETWORK:
        assert torch.equal(getattr(deformed, name), getattr(prims, name)), name
        rows = {tuple(r.flatten().tolist()) for r in getattr(prims, name)}
        assert all(tuple(r.flatten().tolist()) in rows for r in getattr(halved, name)), name
    assert render(deformed, cam, near=0.05).meta["visible"] > 0 and render(halved, cam, near=0.05).meta["visible"] > 0


def test_data_parallel_training_sends_the_cameras_light():
    """Rank 0 sends the cameras as JSON (core/trainer/dataparallel.py): the light comes back equal."""
    import json

    from radfield.core.trainer.dataparallel import camera_from_meta, camera_meta

    for light in (POINT, SUN, None):
        cam = Camera(fx=20.0, fy=21.0, cx=8.0, cy=7.5, width=16, height=15, c2w=look_at((2.0, 0.5, 0.3), (0, 0, 0)),
                     name="c", conditions={"time": 0.25}).at(light=light)
        back = camera_from_meta(json.loads(json.dumps(camera_meta(cam))), cam.c2w)
        assert back.conditions.get("light") == light and torch.equal(back.c2w, cam.c2w)
        assert dict(back.conditions) == dict(cam.conditions) and back.conditions["time"] == 0.25
        assert (back.fx, back.fy, back.cx, back.cy, back.width, back.height, back.name) == \
            (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, cam.name)


def test_peak_density_joining_and_the_slow_reference_follow_the_parent_kind(render_scene):
    prims, cam = scene(render_scene, "neural-relight")
    spec = kinds.get("neural-relight")
    static = spec.at_view(prims, cam)
    torch.testing.assert_close(spec.peak_density(prims, samples=32), kinds.get("neural").peak_density(static, samples=32),
                               rtol=0, atol=0)
    # joining a model of a narrower colour network pads it with W2 = 0 units: its colours stay
    other = prims.select(slice(0, 4))
    narrow = replace(other, color_w1=other.color_w1[:, :5], color_b1=other.color_b1[:, :5],
                     color_w2=other.color_w2[:, :, :5])
    _, padded = spec.harmonise(prims, narrow)
    assert padded.color_w1.shape[1] == prims.color_w1.shape[1]
    torch.testing.assert_close(spec.at_view(padded, cam).sh, spec.at_view(narrow, cam).sh, rtol=0, atol=1e-14)
    # the slow reference draws a relightable model under the view's light
    gaussians, gcam = scene(render_scene, "gaussian-relight")
    small = gcam.scaled(0.5)
    slow = reference_render(gaussians, small, background=BG, near=0.05)
    assert (render(gaussians, small, background=BG, near=0.05).color - slow).abs().max() < 1e-6
