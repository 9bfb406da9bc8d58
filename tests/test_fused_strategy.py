"""The densification statistics of a view in one C++ pass (fused.gaussian_accumulate /
neural_accumulate) against the readable torch twin of strategy._Strategy.accumulate."""

import os

import pytest
import torch

from radfield.core.backends import fused
from radfield.core.geometry.cameras import Camera, look_at
from radfield.core.train.strategy import GAUSSIAN_RADIUS_SIGMAS, in_frustum
from radfield.core.trainer.loop import make_strategy

IN_CI = os.environ.get("CI", "").strip().lower() == "true"
pytestmark = pytest.mark.skipif(not IN_CI and not fused.available(), reason="fused CPU kernels unavailable")


# the scene and the densify section: conftest.strategy_scene, densify_config (shared with tests/test_backends.py)
@pytest.mark.parametrize("kind", ["gaussian", "neural"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_accumulate_fused_matches_torch_twin(kind, dtype, monkeypatch, strategy_scene, densify_config):
    params, grads, cam = strategy_scene(kind, dtype)
    strategy = make_strategy(kind, densify_config(), extent=1.0, near=0.05, max_primitives=None, initial_count=4000)
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


def test_frustum_of_fused_accumulate_equals_in_frustum_near_the_boundary(strategy_scene):
    """Spheres that just reach or just miss a side plane (radius = distance · (1 ± 1e-4)) decide alike."""
    from radfield.core.train.strategy import side_normals
    params, grads, cam = strategy_scene("gaussian", torch.float32, p=3000, seed=5)
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
