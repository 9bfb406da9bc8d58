"""The kernel-backend seam (radfield.core.backends): every backend available on this machine against
the readable torch twins — whole renders (image and every parameter gradient), the loss, the
densification statistics and the σ ≥ 0 projection — and the switch that forces the twins.

The op-by-op comparisons of the fused C++ kernels (block kernels, per-view preparation, bounds)
are tests/test_fused.py's.
"""

import os

import pytest
import torch

from radfield.core import backends
from radfield.core.backends import fused
from radfield.core.geometry.cameras import Camera, look_at
from radfield.core.render.rasterize import render
from radfield.core.train import losses
from radfield.core.train.positivity import NonNegativeDensity
from radfield.core.trainer.loop import make_strategy
from shared_helpers import TOL32, assert_renders_close, float64_twin, render_with_grads

IN_CI = os.environ.get("CI", "").strip().lower() == "true"


def cpu_backends(dtype=torch.float64) -> list[str]:
    """Every backend that runs CPU tensors of `dtype` here ("torch" included: the seam's own path)."""
    return backends.available("cpu", dtype)


def test_fused_cpu_backend_is_available():
    """CI fails here when the fused CPU kernels do not build; elsewhere a machine without a
    compiler runs the torch twins alone (and skips this check)."""
    if not IN_CI and backends.FUSED_CPU not in cpu_backends():
        pytest.skip(f"fused CPU kernels unavailable: {backends.why_not(backends.FUSED_CPU)}")
    for dtype in (torch.float32, torch.float64):
        assert backends.available("cpu", dtype)[:1] == [backends.FUSED_CPU], backends.why_not(backends.FUSED_CPU)
        assert backends.select("cpu", dtype, kind="neural") == backends.FUSED_CPU
    # what it cannot run falls to the twins
    assert backends.available("cpu", torch.float16) == [backends.TORCH]
    assert backends.available("meta", torch.float32) == [backends.TORCH]


def assert_renders_match(fast, grads_fast, slow, grads_slow, tol, scene=None):
    """The same counts, and images and gradients within `tol`: of each other in float64; in float32
    each within `tol` of the twin in float64 on the same rounded inputs of `scene` (prims, camera;
    shared_helpers.float64_twin)."""
    assert slow.meta["contributing_pairs"] > 100
    # evaluated pairs differ by design (the fused kernel skips a pixel as soon as it terminates,
    # the torch twin only between chunks); everything else is the same count
    evaluated = fast.meta.pop("pairs"), slow.meta.pop("pairs")
    assert fast.meta == slow.meta and evaluated[0] <= evaluated[1]
    if fast.color.dtype == torch.float64:
        assert_renders_close(fast, grads_fast, slow, grads_slow, tol)
        return
    exact, grads_exact = float64_twin(*scene)
    assert_renders_close(fast, grads_fast, exact, grads_exact, tol, "fast float32: ")
    assert_renders_close(slow, grads_slow, exact, grads_exact, tol, "torch float32: ")


@pytest.mark.parametrize("backend", cpu_backends())
@pytest.mark.parametrize("kind", ["neural", "neural-window", "gaussian"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_render_matches_the_torch_twin(backend, kind, dtype, render_scene):
    """The scene: conftest.render_scene (the fused kernels' hard cases; well posed in float32:
    tests/test_triton.py, test_the_float32_scenes_are_well_posed)."""
    prims, cam = render_scene(kind, dtype)
    fast, grads_fast = render_with_grads(prims, cam, backend)
    slow, grads_slow = render_with_grads(prims, cam, backends.TORCH)
    tol = dict(rtol=1e-9, atol=1e-10) if dtype == torch.float64 else TOL32
    assert_renders_match(fast, grads_fast, slow, grads_slow, tol, scene=(prims, cam))


@pytest.mark.parametrize("backend", cpu_backends())
def test_render_matches_the_torch_twin_at_another_width(backend, render_scene):
    """The fused view kernels unroll the default 8 hidden units; any other width takes the run-time
    loop, which must agree with the torch twin as well (images and every gradient, float64)."""
    prims, cam = render_scene("neural", torch.float64, hidden=5)
    assert prims.hidden == 5
    fast, grads_fast = render_with_grads(prims, cam, backend)
    slow, grads_slow = render_with_grads(prims, cam, backends.TORCH)
    assert_renders_match(fast, grads_fast, slow, grads_slow, dict(rtol=1e-9, atol=1e-10))


@pytest.mark.parametrize("backend", cpu_backends())
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_loss_matches_the_torch_twin(backend, dtype):
    """ssim ("valid", "same", with a valid-pixel mask), the photometric loss and the anisotropy
    on `backend` equal the twins', values and gradients."""
    g = torch.Generator().manual_seed(4)
    img, ref = torch.rand(24, 30, 3, generator=g, dtype=dtype), torch.rand(24, 30, 3, generator=g, dtype=dtype)
    mask = torch.ones(24, 30, dtype=torch.bool)
    mask[:3] = False
    log_scales = torch.randn(50, 3, generator=g, dtype=dtype)
    log_scales[0] = 0.1                  # isotropic: std 0, and a three-way tie of the minimum

    def run(name):
        with backends.using(name):
            x, x2, x3, ls = (t.clone().requires_grad_() for t in (img, img, img, log_scales))
            values = [losses.ssim(x, ref, "valid", mask), losses.dssim(x, ref, mask), losses.ssim(x2, ref),
                      losses.photometric(x3, ref, 0.2), losses.anisotropy(ls)]
            sum(values).backward()
            return [v.detach() for v in values] + [x.grad, x2.grad, x3.grad, ls.grad]

    tol = dict(rtol=1e-5, atol=1e-6) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-12)
    for fast, slow in zip(run(backend), run(backends.TORCH)):
        torch.testing.assert_close(fast, slow, **tol)


@pytest.mark.parametrize("backend", cpu_backends())
@pytest.mark.parametrize("kind", ["neural", "gaussian"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_densification_statistics_match_the_torch_twin(backend, kind, dtype, strategy_scene, densify_config):
    """A view's statistics of the kind's strategy (core/train/strategy.py: accumulate) on `backend`
    equal the twin's: the same primitives counted visible, the same summed signal (the scene:
    conftest.strategy_scene, seen from a second side too)."""
    p = 3000
    params, grads, cam = strategy_scene(kind, dtype, p=p)
    cams = [cam, Camera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, look_at((-2.5, 2.0, 0.5), (0.0, 0.0, 0.2)))]
    strategy = make_strategy(kind, densify_config(), extent=1.0, near=0.05, max_primitives=None, initial_count=p)

    def run(name):
        with backends.using(name):
            state = {k: v.to(dtype) for k, v in strategy.init_state(p, "cpu").items()}
            for cam in cams:
                strategy.accumulate(state, params, grads, cam, step=1)
            return state

    fast, slow = run(backend), run(backends.TORCH)
    assert torch.equal(fast["count"], slow["count"]) and set(slow["count"].unique().tolist()) == {0.0, 1.0, 2.0}
    tol = dict(rtol=1e-5, atol=1e-9) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(fast["grad"], slow["grad"], **tol)


@pytest.mark.parametrize("backend", cpu_backends())
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_nonnegative_projection_matches_the_torch_twin(backend, dtype):
    """The σ ≥ 0 projection after a step (core/train/positivity.py) on `backend` equals the twin's
    on every primitive: inside the cone, ties, the polar cone."""
    g = torch.Generator().manual_seed(5)
    w2 = (torch.randn(300, 8, generator=g) * 0.4).to(dtype)
    b2 = (torch.randn(300, generator=g) * 0.3).to(dtype)
    w2[:20] = 0.25
    b2[20:40] = w2[20:40].abs().sum(-1) + 0.1
    b2[40:60] = -w2[40:60].abs().amax(-1) - 0.1
    rule = NonNegativeDensity([], threshold=180.0, near=0.01)

    def run(name):
        params = {"means": torch.zeros(300, 3, dtype=dtype), "log_scales": torch.zeros(300, 3, dtype=dtype),
                  "w2": w2.clone(), "b2": b2.clone()}
        with backends.using(name):
            rule.apply(params, 0)
        return params["w2"], params["b2"]

    tol = dict(rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-12)
    for fast, slow in zip(run(backend), run(backends.TORCH)):
        torch.testing.assert_close(fast, slow, **tol)
    assert not torch.equal(run(backends.TORCH)[0], w2)   # the projection acted


def test_the_switch_forces_the_torch_twins(monkeypatch, render_scene):
    """RADFIELD_KERNELS=torch: no backend but the twins is available, every op asks its caller
    to run the twin, and a render calls no fused view kernel."""
    calls = []
    for name in ("neural_view", "gaussian_view", "ssim_map", "anisotropy"):
        original = getattr(fused, name)
        monkeypatch.setattr(fused, name, lambda *a, _f=original, _n=name, **k: calls.append(_n) or _f(*a, **k))
    monkeypatch.setenv("RADFIELD_KERNELS", "torch")
    assert backends.available("cpu", torch.float32) == [backends.TORCH] == backends.available()
    assert backends.select("cpu", torch.float64, kind="gaussian") == backends.TORCH
    assert backends.why_not(backends.FUSED_CPU) == "RADFIELD_KERNELS=torch"
    for op in (backends.view_op("neural"), backends.view_op("gaussian"), *backends.Op):
        assert backends.kernel(op, "cpu", torch.float32) is None, op
    assert not fused.available()
    for kind in ("neural", "gaussian"):
        out = render(*render_scene(kind, torch.float32))
        assert out.meta["contributing_pairs"] > 100
    losses.ssim(torch.rand(16, 16, 3), torch.rand(16, 16, 3))
    losses.anisotropy(torch.randn(5, 3))
    assert calls == []


def test_a_registered_backend_runs_where_it_says_it_runs():
    """The room for another backend (a GPU one): registered ahead of fused-cpu for float64 CPU
    tensors only, with an implementation of `anisotropy`, it is the one the loss calls there, the
    twin (or fused-cpu) runs elsewhere, and kinds it has no view for are not offered to it."""
    calls = []

    def anisotropy(log_scales):
        calls.append(log_scales.dtype)
        return losses._anisotropy(log_scales)

    backends.register(backends.Backend("test-f64", lambda device, dtype: dtype == torch.float64
                                       and (device is None or torch.device(device).type == "cpu"), rank=0))
    try:
        backends.implement("anisotropy", "test-f64", anisotropy)
        assert backends.names()[0] == "test-f64"
        assert backends.available("cpu", torch.float64)[0] == "test-f64"
        assert "test-f64" not in backends.available("cpu", torch.float32)
        assert "test-f64" not in backends.available("cpu", torch.float64, kind="neural")
        log_scales = torch.randn(7, 3, dtype=torch.float64)
        torch.testing.assert_close(losses.anisotropy(log_scales), losses._anisotropy(log_scales))
        losses.anisotropy(log_scales.float())
        assert calls == [torch.float64]
        with backends.using(backends.TORCH):
            losses.anisotropy(log_scales)
        assert calls == [torch.float64]
    finally:
        backends.unregister("test-f64")
    assert "test-f64" not in backends.names() and backends.kernel("anisotropy", "cpu", torch.float64) is not anisotropy


def test_an_unknown_op_fails_loudly():
    """A misspelt op is an error where it is registered and where it is asked for, not a silent twin;
    the ops are the typed keys of backends.Op (their plain strings are the same keys)."""
    with pytest.raises(KeyError, match="unknown backend op 'anisotropi'"):
        backends.kernel("anisotropi", "cpu", torch.float32)
    with pytest.raises(KeyError, match="unknown backend op 'ssim'"):
        backends.implement("ssim", backends.FUSED_CPU, lambda *a: None)
    assert backends.kernel("anisotropy", "cpu", torch.float32) is backends.kernel(backends.Op.ANISOTROPY, "cpu", torch.float32)
    if fused.available():
        assert backends.kernel(backends.Op.ANISOTROPY, "cpu", torch.float32) is fused.anisotropy
    assert backends.view_op("neural") == "view.neural"
