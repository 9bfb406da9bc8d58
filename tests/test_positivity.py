"""Non-negative density of neural primitives seen from narrow view cones (radfield.core.train.positivity)
and the absolute frequency bound (radfield.core.train.frequency, train.frequency_bound)."""

import math
import os

import pytest
import torch

from radfield.core import kinds
from radfield.core.backends import fused
from radfield.core.geometry.cameras import Camera, look_at
from radfield.errors import RadfieldError
from radfield.core.train.frequency import FrequencyCap
from radfield.core.train.positivity import NonNegativeDensity, project_nonnegative, view_cone_half_angle
from radfield.core.kinds import random_neural
from radfield.core.render.rasterize import render
from radfield.core.train.strategy import in_frustum
from radfield.core.trainer.loop import train
from radfield.pipeline.config import load_config, load_defaults
from shared_helpers import projection_rows

BG = (1.0, 1.0, 1.0)


def camera(eye, size=16, f=20.0, target=(0.0, 0.0, 0.0)) -> Camera:
    return Camera(fx=f, fy=f, cx=size / 2, cy=size / 2, width=size, height=size, c2w=look_at(eye, target))


def reference_projection(w2, b2):
    """The projection onto ‖W2‖₁ ≤ b2 by brute force: minimise the squared distance over λ ≥ 0 of
    (S_λ(W2), b2 + λ) by bisection on g(λ) = ‖S_λ(W2)‖₁ − b2 − λ (float64)."""
    w2, b2 = w2.double(), b2.double()
    lo, hi = torch.zeros_like(b2), w2.abs().amax(-1) + b2.abs() + 1
    for _ in range(200):
        mid = (lo + hi) / 2
        over = (w2.abs() - mid[:, None]).clamp_min(0).sum(-1) - b2 - mid > 0
        lo, hi = torch.where(over, mid, lo), torch.where(over, hi, mid)
    inside = w2.abs().sum(-1) <= b2 + 1e-6 * (b2.abs() + 1)
    lam = torch.where(inside, 0.0, lo)
    return (torch.sign(w2) * (w2.abs() - lam[:, None]).clamp_min(0),
            torch.where(inside, b2, (b2 + lam).clamp_min(0)))


def views(n=4):
    return [camera((3 * math.cos(a), 3 * math.sin(a), 0.5)) for a in torch.linspace(0, 5, n).tolist()]


def images_of(prims, cams):
    with torch.no_grad():
        return torch.stack([render(prims, c, background=BG).color.clamp(0, 1) for c in cams])


def two_clusters():
    """Primitives around A = 0, seen by 3 cameras within 5° of +x (a narrow cone), and around
    B = (5, 0, 0), seen by 3 cameras 90° apart (a wide one); narrow fields of view, so no camera
    sees the other cluster."""
    narrow = [camera((3 * math.cos(a), 3 * math.sin(a), 0.0), f=60.0, target=(0.0, 0.0, 0.0))
              for a in (-0.09, 0.0, 0.09)]
    wide = [camera(eye, f=60.0, target=(5.0, 0.0, 0.0)) for eye in ((5.0, 3.0, 0.0), (5.0, 0.5, 2.96), (5.0, -3.0, 0.0))]
    prims = random_neural(40, hidden=6, extent=0.3, scale=0.08, seed=2)   # W2 ~ ±0.3, b2 = 1: many outside C
    prims.means[20:, 0] += 5.0
    return narrow + wide, prims


def reference_half_angle(means, radius, cams, near):
    """β of eq. (3) by the obvious loops (float64)."""
    out = []
    for p in range(len(means)):
        dirs = [torch.nn.functional.normalize(c.center.double() - means[p].double(), dim=0) for c in cams
                if bool(in_frustum(means[p:p + 1], radius[p:p + 1], c, near)[0])]
        if not dirs:
            out.append(0.0)
            continue
        mean = torch.nn.functional.normalize(torch.stack(dirs).sum(0), dim=0)
        out.append(max(math.degrees(math.acos(min(1.0, float(d @ mean)))) for d in dirs))
    return torch.tensor(out, dtype=torch.float64)


def test_the_projection_is_the_nearest_point_of_the_cone():
    g = torch.Generator().manual_seed(0)
    w2, b2 = torch.randn(500, 8, generator=g), torch.randn(500, generator=g) * 2
    w2[:4], b2[:4] = 0.25, torch.tensor([2.0, 1.99, -0.3, -5.0])  # ties; inside by a hair; polar
    new_w2, new_b2 = project_nonnegative(w2, b2)
    ref_w2, ref_b2 = reference_projection(w2, b2)
    assert torch.allclose(new_w2.double(), ref_w2, atol=1e-5) and torch.allclose(new_b2.double(), ref_b2, atol=1e-5)
    assert (new_w2.abs().sum(-1) <= new_b2 + 1e-5).all()
    inside = w2.abs().sum(-1) <= b2 + 1e-6 * (b2.abs() + 1)
    assert inside.any() and (~inside).any()
    assert torch.equal(new_w2[inside], w2[inside]) and torch.equal(new_b2[inside], b2[inside])  # bit for bit
    assert new_b2[3] == 0 and (new_w2[3] == 0).all()  # the polar cone goes to the apex
    # idempotent, and no point of the cone is nearer than the projection (random cone points)
    again = project_nonnegative(new_w2, new_b2)
    assert torch.equal(again[0], new_w2) and torch.equal(again[1], new_b2)
    probe_w2 = new_w2 + 0.05 * torch.randn(500, 8, generator=g)
    probe_b2 = probe_w2.abs().sum(-1) + 0.05 * torch.rand(500, generator=g)
    dist = lambda a, b: (a - w2).square().sum(-1) + (b - b2).square()
    assert (dist(new_w2, new_b2) <= dist(probe_w2, probe_b2) + 1e-5).all()


def test_the_view_cone_half_angle_against_loops():
    cams, prims = two_clusters()
    radius = prims.scales.amax(-1)
    beta = view_cone_half_angle(prims.means, radius, cams, 0.01)
    assert torch.allclose(beta.double(), reference_half_angle(prims.means, radius, cams, 0.01), atol=1e-3)
    assert (beta[:20] < 10).all() and (beta[20:] > 60).all()
    g = torch.Generator().manual_seed(1)
    means = torch.rand(200, 3, generator=g) * 2 - 1
    cams = views(7)
    assert torch.allclose(view_cone_half_angle(means, torch.full((200,), 0.1), cams, 0.01).double(),
                          reference_half_angle(means, torch.full((200,), 0.1), cams, 0.01), atol=1e-3)


def test_training_keeps_every_density_non_negative():
    cams = views()
    truth = random_neural(30, hidden=6, extent=0.5, scale=0.2, seed=1)
    images = images_of(truth, cams)
    start = random_neural(30, hidden=6, extent=0.5, scale=0.15, seed=2)  # W2 ~ ±0.3, b2 = 1: mostly outside
    assert (start.w2.abs().sum(-1) > start.b2).any()
    cfg = load_defaults()["train"]
    cfg.update(iterations=10, sh_degree=0, nonnegative_density=180.0, checkpoint_every=5)
    cfg["densify"].update(start=4, stop=8, every=4)
    run = dict(background=BG, extent=3.0, seed=0)
    trained = train(start, cams, images, cfg, **run).primitives()
    assert (trained.w2.abs().sum(-1) <= trained.b2 + 1e-5).all()
    # σ(x) = W2 · cos(ω0 (W1 u + b1)) + b2 at random points of each primitive's unit ball
    u = torch.nn.functional.normalize(torch.randn(len(trained), 64, 3), dim=-1) * torch.rand(len(trained), 64, 1)
    phase = trained.omega0 * (torch.einsum("pnk,psk->psn", trained.w1, u) + trained.b1[:, None])
    sigma = (trained.w2[:, None] * torch.cos(phase)).sum(-1) + trained.b2[:, None]
    assert sigma.min() >= -1e-5
    # without it the same run has negative density somewhere
    free = train(start, cams, images, {**cfg, "nonnegative_density": 0.0}, **run).primitives()
    assert (free.w2.abs().sum(-1) > free.b2 * 1.01).any()


def test_only_narrow_view_cones_are_projected_and_a_resumed_run_is_the_same(tmp_path, kill_and_resume):
    cams, start = two_clusters()
    truth = random_neural(40, hidden=6, extent=0.3, scale=0.1, seed=5)
    truth.means[20:, 0] += 5.0
    images = images_of(truth, cams)
    cfg = load_defaults()["train"]
    cfg.update(iterations=10, sh_degree=0, nonnegative_density=30.0, checkpoint_every=5)
    cfg["densify"].update(start=4, stop=8, every=4, grad_threshold=1e-5)
    run = dict(background=BG, extent=3.0, seed=0)
    whole = train(start, cams, images, cfg, **run)
    trained = whole.primitives()
    assert len(trained) != len(start)  # population control acted
    inside = trained.w2.abs().sum(-1) <= trained.b2 + 1e-5
    near_a = trained.means[:, 0] < 2.5
    assert inside[near_a].all() and not inside[~near_a].all()

    _, resumed = kill_and_resume(start, cams, images, cfg, tmp_path / "checkpoint.safetensors", kill_at=7, **run)
    for name in whole.params:
        assert torch.equal(whole.params[name], resumed.params[name]), name


def test_gaussians_are_not_projected():
    """The projection is a training rule of the neural kind alone (radfield.core.kinds)."""
    cfg = load_defaults()["train"]
    cfg["nonnegative_density"] = 180.0
    assert not any(isinstance(rule, NonNegativeDensity)
                   for rule in kinds.get("gaussian").training_rules(views(), cfg, {}, near=0.01))
    rules = kinds.get("neural").training_rules(views(), cfg, {"omega0": 30.0, "window": False}, near=0.01)
    assert [rule.enabled for rule in rules if isinstance(rule, NonNegativeDensity)] == [True]
    assert NonNegativeDensity.for_training(views(), cfg, near=0.01).enabled
    with pytest.raises(ValueError):
        NonNegativeDensity(views(), threshold=200.0, near=0.01)


def test_the_absolute_frequency_bound_holds_after_training():
    cams = views()
    truth = random_neural(30, hidden=6, extent=0.5, scale=0.2, seed=1)
    start = random_neural(30, hidden=6, extent=0.5, scale=0.15, seed=2, omega0=30.0)
    cfg = load_defaults()["train"]
    cfg.update(iterations=6, sh_degree=0, frequency_cap=0.0, frequency_bound=math.pi)
    cap = FrequencyCap.for_training(cams, cfg, omega0=30.0, near=0.01)
    assert cap.enabled and cap.absolute == math.pi
    assert (30.0 * start.w1.norm(dim=-1) > math.pi).any()  # the bound has work to do
    trained = train(start, cams, images_of(truth, cams), cfg, background=BG, extent=3.0, seed=0).primitives()
    assert (trained.omega0 * trained.w1.norm(dim=-1) <= math.pi * (1 + 1e-5)).all()
    # together with the footprint cap the smaller of the two binds
    both = FrequencyCap(cams, factor=1e6, omega0=30.0, near=0.01, absolute=2.0)
    params = {"means": start.means, "log_scales": start.log_scales}
    assert torch.allclose(both.bound(params), torch.full((30,), 2.0 / 30.0))


@pytest.mark.parametrize("key, value", [("frequency_bound", -1.0), ("nonnegative_density", -1.0),
                                        ("nonnegative_density", 181.0)])
def test_bad_values_are_one_line_errors(key, value):
    with pytest.raises(RadfieldError, match=f"train.{key}"):
        load_config(None, [f"train.{key}={value}"])


@pytest.mark.skipif(os.environ.get("CI", "").strip().lower() != "true" and not fused.available(),
                    reason="fused CPU kernels unavailable")   # in CI a failed build fails here
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_projection_matches_the_torch_twin(dtype):
    """core/backends/csrc/positivity_kernels.cpp against project_nonnegative: inside rows, ties, the polar
    cone, zeros, widths 1-16; only the masked rows change."""
    g = torch.Generator().manual_seed(5)
    for width in (1, 3, 8, 16):
        w2, b2, mask = projection_rows(width, dtype, g)
        expect_w2, expect_b2 = project_nonnegative(w2, b2)
        fused_w2, fused_b2 = w2.clone(), b2.clone()
        fused.project_nonnegative_(fused_w2, fused_b2, mask)
        tol = dict(rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-12)
        torch.testing.assert_close(fused_w2[mask], expect_w2[mask], **tol)
        torch.testing.assert_close(fused_b2[mask], expect_b2[mask], **tol)
        assert torch.equal(fused_w2[~mask], w2[~mask]) and torch.equal(fused_b2[~mask], b2[~mask])
        assert bool((fused_w2[mask].abs().sum(-1) <= fused_b2[mask] + 1e-5).all())
