"""The densification statistics of a view in one C++ pass (fused.gaussian_accumulate /
neural_accumulate) against the readable torch twin of strategy._Strategy.accumulate."""

import os

import pytest
import torch

from radfield.core.backends import fused
from radfield.core.geometry.cameras import Camera, look_at
from radfield.core.train.strategy import GAUSSIAN_RADIUS_SIGMAS, in_frustum, make_strategy

IN_CI = os.environ.get("CI", "").strip().lower() == "true"
pytestmark = pytest.mark.skipif(not IN_CI and not fused.available(), reason="fused CPU kernels unavailable")

DENSIFY = {"start": 1, "stop": 100, "every": 10, "grad_threshold": 1e-3, "grow_scale": 0.01, "prune_scale": 0.5,
           "prune_threshold": 1e-6, "gaussian": {"grad_threshold": 2e-4, "prune_scale": 0.1, "min_opacity": 0.005,
                                                  "opacity_reset_every": 3000}}


def _scene(kind, dtype, p=4000, seed=0):
    g = torch.Generator().manual_seed(seed)
    # means spread well beyond the frustum, scales from tiny to large: both outcomes of the test
    params = {"means": (torch.rand(p, 3, generator=g, dtype=dtype) * 2 - 1) * 3,
              "log_scales": torch.log(torch.rand(p, 3, generator=g, dtype=dtype) * 0.8 + 1e-3)}
    if kind == "gaussian":
        grads = {"means": torch.randn(p, 3, generator=g, dtype=dtype) * 1e-4}
    else:
        grads = {"w1": torch.randn(p, 8, 3, generator=g, dtype=dtype), "b1": torch.randn(p, 8, generator=g, dtype=dtype),
                 "w2": torch.randn(p, 8, generator=g, dtype=dtype), "b2": torch.randn(p, generator=g, dtype=dtype)}
    cam = Camera(50.0, 45.0, 31.0, 24.5, 64, 48, look_at((0.3, -3.5, 1.0), (0.0, 0.0, 0.2)))
    return params, grads, cam


@pytest.mark.parametrize("kind", ["gaussian", "neural"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_accumulate_fused_matches_torch_twin(kind, dtype, monkeypatch):
    params, grads, cam = _scene(kind, dtype)
    strategy = make_strategy(kind, DENSIFY, extent=1.0, near=0.05, max_primitives=None, initial_count=4000)
    states = []
    for twin in (False, True):
        if twin:
            monkeypatch.setenv("RADFIELD_KERNELS", "torch")
        state = {k: v.to(dtype) for k, v in strategy.init_state(4000, "cpu").items()}
        state["grad"] += 0.25   # the op adds into what is there
        for view in range(2):   # two views: counts of 0, 1 and 2
            c = cam if view == 0 else Camera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height,
                                             look_at((-2.5, 2.0, 0.5), (0.2, 0.0, 0.0)))
            strategy.accumulate(state, params, grads, c, step=1)
        states.append(state)
    fast, slow = states
    assert torch.equal(fast["count"], slow["count"])          # the same primitives visible, in every view
    assert set(slow["count"].unique().tolist()) == {0.0, 1.0, 2.0}
    tol = dict(rtol=1e-5, atol=1e-9) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(fast["grad"], slow["grad"], **tol)
    assert (fast["grad"][slow["count"] == 0] == 0.25).all()   # nothing added where never visible


def test_frustum_of_fused_accumulate_equals_in_frustum_near_the_boundary():
    """Spheres that just reach or just miss a side plane (radius = distance · (1 ± 1e-4)) decide alike."""
    from radfield.core.train.strategy import side_normals
    params, grads, cam = _scene("gaussian", torch.float32, p=3000, seed=5)
    w2c = cam.w2c.float()
    p = params["means"] @ w2c[:3, :3].T + w2c[:3, 3]
    distance = (p @ side_normals(cam, p).T).amin(-1)
    outside = distance < -1e-3
    jitter = torch.where(torch.rand(3000, generator=torch.Generator().manual_seed(2)) < 0.5, 1 + 1e-4, 1 - 1e-4)
    radius = torch.where(outside, -distance * jitter, 0.01)
    params["log_scales"] = torch.log(radius / GAUSSIAN_RADIUS_SIGMAS)[:, None].expand(-1, 3).contiguous()
    radius = GAUSSIAN_RADIUS_SIGMAS * torch.exp(params["log_scales"].amax(-1))
    visible = in_frustum(params["means"], radius, cam, 0.05)
    grad, count = torch.zeros(3000), torch.zeros(3000)
    fused.gaussian_accumulate(grad, count, params["means"], params["log_scales"], grads["means"], w2c[:3],
                              side_normals(cam, params["means"]), GAUSSIAN_RADIUS_SIGMAS, 0.05, cam.fx, cam.fy,
                              cam.width, cam.height)
    assert torch.equal(count.bool(), visible)
    decided = visible[outside].float().mean()
    assert outside.sum() > 500 and 0.3 < decided < 0.7   # about half of the near misses are in
