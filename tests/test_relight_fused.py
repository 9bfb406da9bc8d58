"""The fused colour of the relightable kinds (fused.relight_view_dc, core/backends/csrc/relight_kernels.cpp)
against its torch twin (core/kinds/relight.py: view_sh on the torch backend): the degree-0 SH of a
view and the gradients of every input, for point and directional lights, random rotations and both
kinds; float64 gradcheck of the op; whole renders and their gradients on fused-cpu against torch;
and the twin where the op does not apply (higher SH bands, RADFIELD_KERNELS=torch).
"""

import os
from dataclasses import replace

import pytest
import torch

from radfield.core import backends, kinds
from radfield.core.backends import fused
from radfield.core.geometry.cameras import Camera, Light, look_at
from radfield.core.kinds import RelightGaussians, RelightNeuralPrimitives, random_gaussians, random_neural
from radfield.core.kinds.relight import init_network
from radfield.core.render.rasterize import render

IN_CI = os.environ.get("CI", "").strip().lower() == "true"
pytestmark = pytest.mark.skipif(not IN_CI and not fused.available(), reason="fused CPU kernels unavailable")

POINT = Light(position=(1.0, -2.5, 1.5), intensity=9.0)
SUN = Light(direction=(-0.3, 0.5, -0.8124038404635961), intensity=1.3)
LIGHTS = {"point": POINT, "directional": SUN}
KINDS = ("neural-relight", "gaussian-relight")
INPUTS = ("means", "quats", "sh", "color_w1", "color_b1", "color_w2", "color_b2")


def relight_model(kind, num=14, hidden=12, sh_degree=0, dtype=torch.float64, seed=3):
    """A relightable model of `kind` with random rotations and a random network whose output is
    clearly non-zero; primitive 0 has a hidden unit above softplus's threshold (20: the identity)."""
    if kind == "neural-relight":
        static = random_neural(num, sh_degree=sh_degree, hidden=8, scale=0.3, extent=0.6, seed=seed, dtype=dtype)
    else:
        static = random_gaussians(num, sh_degree=sh_degree, scale=0.15, extent=0.6, seed=seed, dtype=dtype)
    g = torch.Generator().manual_seed(seed)
    net = init_network(num, hidden, seed, dtype)
    net["color_w2"] = torch.randn(num, 3, hidden, generator=g, dtype=dtype) * 0.4
    net["color_b2"] = torch.randn(num, 3, generator=g, dtype=dtype) * 0.1
    net["color_b1"][0, 0] = 25.0
    quats = torch.randn(num, 4, generator=g, dtype=dtype) * 1.7   # not unit: the op normalises them
    relight_type = RelightNeuralPrimitives if kind == "neural-relight" else RelightGaussians
    fields = {name: getattr(static, name) for name in static.tensors()}
    extra = {"omega0": static.omega0, "window": static.window} if kind == "neural-relight" else {}
    return relight_type(**{**fields, "quats": quats, **net}, **extra)


def camera(light, size=(24, 20)):
    return Camera(fx=30.0, fy=33.0, cx=12.3, cy=9.7, width=size[0], height=size[1],
                  c2w=look_at((0.3, -3.0, 0.5), (0, 0, 0))).at(light=light)


def view_dc_with_grads(prims, cam, backend):
    """The kind's at_view SH on `backend` alone, and the gradient of a random weighting of it
    w.r.t. every input of the colour and the camera centre."""
    with backends.using(backend):
        params = prims.map(lambda t: t.clone().requires_grad_(True))
        c2w = cam.c2w.to(prims.means.dtype).clone().requires_grad_(True)
        sh = kinds.of(params).at_view(params, replace(cam, c2w=c2w)).sh
        weights = torch.randn(sh.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64).to(sh.dtype)
        tensors = [params.tensors()[name] for name in INPUTS] + [c2w]
        grads = torch.autograd.grad((weights * sh).sum(), tensors)
    return sh, dict(zip(INPUTS + ("c2w",), grads))


def test_the_op_is_the_fused_cpu_backends_and_runs_in_view_sh():
    for dtype in (torch.float32, torch.float64):
        assert backends.kernel("relight_view_dc", "cpu", dtype) is fused.relight_view_dc
    prims, cam = relight_model("neural-relight"), camera(POINT)
    with backends.using(backends.FUSED_CPU):
        sh = kinds.of(prims).at_view(prims.map(lambda t: t.requires_grad_(True)), cam).sh
    assert sh.grad_fn is not None and "RelightViewDC" in type(sh.grad_fn).__name__


@pytest.mark.parametrize("light", LIGHTS)
@pytest.mark.parametrize("kind", KINDS)
def test_the_fused_colour_matches_the_torch_twin_values_and_every_gradient(kind, light):
    prims, cam = relight_model(kind), camera(LIGHTS[light])
    fast, grads_fast = view_dc_with_grads(prims, cam, backends.FUSED_CPU)
    slow, grads_slow = view_dc_with_grads(prims, cam, backends.TORCH)
    assert fast.shape == slow.shape == (len(prims), 1, 3)
    assert slow.std() > 0.1   # the network and the light make the colours differ
    torch.testing.assert_close(fast, slow, rtol=1e-12, atol=1e-12)
    for name, g in grads_slow.items():
        assert g.abs().max() > 0, name
        torch.testing.assert_close(grads_fast[name], g, rtol=1e-10, atol=1e-12, msg=lambda m, n=name: f"{n}: {m}")


@pytest.mark.parametrize("light", LIGHTS)
def test_the_fused_colour_in_float32_matches_the_twin(light):
    prims, cam = relight_model("gaussian-relight", dtype=torch.float32), camera(LIGHTS[light])
    fast, grads_fast = view_dc_with_grads(prims, cam, backends.FUSED_CPU)
    slow, grads_slow = view_dc_with_grads(prims, cam, backends.TORCH)
    assert fast.dtype == torch.float32
    torch.testing.assert_close(fast, slow, rtol=1e-5, atol=1e-5)
    for name, g in grads_slow.items():
        torch.testing.assert_close(grads_fast[name], g, rtol=1e-4, atol=1e-4 * float(g.abs().max()),
                                   msg=lambda m, n=name: f"{n}: {m}")


@pytest.mark.parametrize("light", LIGHTS)
def test_the_fused_colour_passes_gradcheck(light):
    prims = relight_model("neural-relight", num=4, hidden=3)
    campos = torch.tensor([0.3, -3.0, 0.5], dtype=torch.float64)
    inputs = [getattr(prims, name).clone().requires_grad_(True) for name in INPUTS] + [campos.requires_grad_(True)]
    assert torch.autograd.gradcheck(lambda *t: fused.relight_view_dc(*t, LIGHTS[light]), inputs, eps=1e-6, atol=1e-7)


@pytest.mark.parametrize("kind", KINDS)
def test_a_relit_render_and_its_gradients_on_fused_cpu_match_the_torch_twins(kind):
    prims, cam = relight_model(kind, num=20), camera(POINT)
    outs, grads = {}, {}
    for backend in (backends.FUSED_CPU, backends.TORCH):
        with backends.using(backend):
            params = prims.map(lambda t: t.clone().requires_grad_(True))
            out = render(params, cam, background=(0.2, 0.3, 0.4), near=0.05)
            weights = torch.randn(out.color.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
            names = list(params.tensors())
            outs[backend] = out.color
            grads[backend] = dict(zip(names, torch.autograd.grad((weights * out.color).sum() + out.alpha.sum(),
                                                                 [params.tensors()[n] for n in names],
                                                                 allow_unused=True)))
    assert (outs[backends.TORCH] - torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)).abs().max() > 0.1   # drawn
    torch.testing.assert_close(outs[backends.FUSED_CPU], outs[backends.TORCH], rtol=1e-9, atol=1e-9)
    for name in INPUTS:
        g_fast, g_slow = grads[backends.FUSED_CPU][name], grads[backends.TORCH][name]
        assert g_slow.abs().max() > 0, name
        torch.testing.assert_close(g_fast, g_slow, rtol=1e-9, atol=1e-9, msg=lambda m, n=name: f"{n}: {m}")


def test_higher_sh_bands_and_forced_twins_run_the_torch_twin(monkeypatch):
    prims, cam = relight_model("neural-relight", sh_degree=1), camera(SUN)
    fast, grads_fast = view_dc_with_grads(prims, cam, backends.FUSED_CPU)   # the op takes degree 0 only
    slow, grads_slow = view_dc_with_grads(prims, cam, backends.TORCH)
    assert torch.equal(fast, slow) and all(torch.equal(grads_fast[n], grads_slow[n]) for n in grads_slow)
    monkeypatch.setenv("RADFIELD_KERNELS", "torch")
    assert backends.kernel("relight_view_dc", "cpu", torch.float64) is None
