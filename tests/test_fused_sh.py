"""The fused SH colour of the trainer's two SH tensors (fused.sh_color_parts) against the torch
twin (core/splat/sh.py: sh_to_color of their concatenation) and by finite differences, and the renderer
and trainer using it (core/splat/sh.py: join_sh)."""

import os

import pytest
import torch

from radfield.core.backends import fused
from radfield.core.geometry.cameras import Camera, look_at
from radfield.core.kinds import random_gaussians
from radfield.core.render.rasterize import render
from radfield.core.splat.sh import join_sh, sh_parts, sh_to_color

IN_CI = os.environ.get("CI", "").strip().lower() == "true"
pytestmark = pytest.mark.skipif(not IN_CI and not fused.available(), reason="fused CPU kernels unavailable")


def _twin(dc, rest, means, campos, degree):
    sh = torch.cat([dc, rest], 1)
    return sh_to_color(sh, torch.nn.functional.normalize(means - campos, dim=-1), degree)


def _case(degree, seed, p=12, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    dc = torch.randn(p, 1, 3, generator=g, dtype=dtype) * 0.5
    rest = torch.randn(p, 15, 3, generator=g, dtype=dtype) * 0.5
    dc[0, 0] = -5.0                        # colour clamped at 0: no gradient there
    means = torch.randn(p, 3, generator=g, dtype=dtype) * 3
    campos = torch.randn(3, generator=g, dtype=dtype)
    return dc, rest, means, campos


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_color_parts_matches_torch_twin_values_and_every_gradient(degree):
    dc, rest, means, campos = _case(degree, degree)
    twin = _twin(dc, rest, means, campos, degree)
    assert (twin == 0).any() and (twin > 0).any()
    torch.testing.assert_close(fused.sh_color_parts(dc, rest, means, campos, degree), twin, rtol=1e-12, atol=1e-12)
    w = torch.randn(twin.shape, generator=torch.Generator().manual_seed(7), dtype=twin.dtype)
    grads = []
    for f in (fused.sh_color_parts, _twin):
        inputs = [t.clone().requires_grad_() for t in (dc, rest, means, campos)]
        grads.append(torch.autograd.grad((w * f(*inputs, degree)).sum(), inputs, allow_unused=True))
    for fast, slow in zip(*grads):   # degree 0: the colour does not depend on the direction
        torch.testing.assert_close(fast, torch.zeros_like(fast) if slow is None else slow, rtol=1e-10, atol=1e-12)
    assert (grads[0][1][:, (degree + 1) ** 2 - 1:] == 0).all()   # bands above the degree: zero gradient
    assert grads[0][0].abs().sum() > 0
    assert (grads[0][2].abs().sum() == 0) == (degree == 0)   # the direction matters from degree 1 on


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_color_parts_by_finite_differences(degree):
    dc, rest, means, campos = _case(degree, 10 + degree, p=4)
    inputs = tuple(t.clone().requires_grad_() for t in (dc, rest[:, :9], means, campos))
    assert torch.autograd.gradcheck(lambda *a: fused.sh_color_parts(*a, min(degree, 2)), inputs, eps=1e-6, atol=1e-7)
    inputs = tuple(t.clone().requires_grad_() for t in (dc, rest, means, campos))
    assert torch.autograd.gradcheck(lambda *a: fused.sh_color_parts(*a, degree), inputs, eps=1e-6, atol=1e-7)


def test_sh_color_parts_float32_equals_the_fused_op_of_the_concatenation():
    """float32: bit for bit the colour and gradients of fused.sh_color on the concatenated tensor
    (the op the renderer used before; the same operations in the same order)."""
    dc, rest, means, campos = (t.float() for t in _case(3, 5, p=3000))
    w = torch.randn(3000, 3, generator=torch.Generator().manual_seed(1))
    out = []
    for parts in (True, False):
        leaves = [t.clone().requires_grad_() for t in (dc, rest, means)]
        if parts:
            color = fused.sh_color_parts(*leaves, campos, 3)
        else:
            color = fused.sh_color(torch.cat(leaves[:2], 1), leaves[2] - campos, 3)
        (w * color).sum().backward()
        out.append([color.detach()] + [t.grad for t in leaves])
    for fast, slow in zip(*out):
        assert torch.equal(fast, slow)


def test_render_and_training_use_the_parts_with_the_same_results():
    """join_sh keeps the parts; render reads them (no gradient through the concatenation) and
    gives the image and gradients of the concatenated tensor; copies of it are plain tensors."""
    prims = random_gaussians(300, sh_degree=3, extent=0.6, scale=0.05, seed=3)
    cam = Camera(40.0, 40.0, 16.0, 16.0, 32, 32, look_at((0.0, -3.0, 0.5), (0.0, 0.0, 0.0)))
    results = []
    for split in (True, False):
        dc, rest = (t.clone().requires_grad_() for t in (prims.sh[:, :1], prims.sh[:, 1:]))
        means = prims.means.clone().requires_grad_()
        sh = join_sh(dc, rest) if split else torch.cat([dc, rest], 1)
        assert (sh_parts(sh) is not None) == split
        out = render(type(prims)(means=means, log_scales=prims.log_scales, quats=prims.quats, sh=sh,
                                 opacities=prims.opacities), cam, sh_degree=2)
        out.color.square().sum().backward()
        results.append((out.color.detach(), dc.grad, rest.grad, means.grad))
    for a, b in zip(*results):
        assert torch.equal(a, b)
    assert sh_parts(join_sh(*(t.detach() for t in (prims.sh[:, :1], prims.sh[:, 1:]))).detach()) is None
