"""The anti-aliasing frequency cap of neural primitives (radfield.core.train.frequency)."""

import math

import pytest
import torch

from radfield.core.geometry.cameras import Camera, look_at
from radfield.core.train.frequency import NYQUIST, FrequencyCap, footprint, view_stack
from radfield.core.kinds import random_neural
from radfield.core.render.rasterize import render
from radfield.core.trainer.loop import initial_state, train
from radfield.pipeline.config import load_defaults

BG = (1.0, 1.0, 1.0)


def camera(eye, size=32, f=40.0, target=(0.0, 0.0, 0.0)) -> Camera:
    return Camera(fx=f, fy=f, cx=size / 2, cy=size / 2, width=size, height=size, c2w=look_at(eye, target))


def reference_footprint(means, max_scale, cameras, near):
    """Per primitive and camera, the obvious loop: project the centre, test it, keep the largest f·r/z."""
    out = []
    for mean, r in zip(means.tolist(), max_scale.tolist()):
        best = 0.0
        for c in cameras:
            x, y, z = (c.w2c[:3, :3] @ torch.tensor(mean, dtype=torch.float64) + c.w2c[:3, 3]).tolist()
            if z <= near:
                continue
            rho = max(c.fx, c.fy) * r / z
            u, v = c.fx * x / z + c.cx, c.fy * y / z + c.cy
            if -rho < u < c.width + rho and -rho < v < c.height + rho:
                best = max(best, rho)
        out.append(best)
    return torch.tensor(out)


def test_footprint_is_the_largest_projected_radius_in_pixels():
    cams = [camera((0.0, -4.0, 0.0)), camera((0.0, -2.0, 0.0), f=30.0), camera((4.0, 0.0, 0.0), size=20)]
    # on the axis of the second camera at depth 2 (ρ = 30 · 0.1 / 2 = 1.5) and of the first at 4 (1.0):
    # the closest wins; one primitive behind every camera but the third, one outside every image
    means = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [6.0, 0.0, 0.0], [0.0, 0.0, 30.0]])
    scales = torch.tensor([0.1, 0.2, 0.1, 0.1])
    got = footprint(means, scales, view_stack(cams), near=0.01)
    assert got[0] == pytest.approx(max(30 * 0.1 / 2, 40 * 0.1 / 4, 40 * 0.1 / 4))
    assert got[1] == pytest.approx(2 * got[0])
    assert got[2] == 0.0 and got[3] == 0.0
    # many random primitives and cameras against the loop
    g = torch.Generator().manual_seed(0)
    cams = [camera((3 * math.cos(a), 3 * math.sin(a), 0.5 * math.sin(3 * a)), size=24 + 8 * k, f=30.0 + 5 * k)
            for k, a in enumerate(torch.linspace(0, 6, 21).tolist())]
    means = torch.rand(300, 3, generator=g) * 6 - 3
    scales = torch.rand(300, generator=g) * 0.2
    assert torch.allclose(footprint(means, scales, view_stack(cams), 0.01),
                          reference_footprint(means, scales, cams, 0.01), rtol=1e-5, atol=1e-6)


def test_the_cap_projects_rows_onto_the_bound_and_is_idempotent():
    cams = [camera((0.0, -3.0, 0.0))]
    prims = random_neural(40, hidden=6, extent=0.3, scale=0.05, seed=4)
    params = {"means": prims.means, "log_scales": prims.log_scales, "w1": prims.w1 * torch.logspace(-3, 0, 40)[:, None, None]}  # some rows within, some over
    params["means"][0] = torch.tensor([0.0, 0.0, 50.0])  # outside the image: no bound
    cap = FrequencyCap(cams, factor=NYQUIST, omega0=30.0, near=0.01)
    bound = cap.bound(params)
    assert math.isinf(bound[0]) and torch.isfinite(bound[1:]).all()
    rho = footprint(params["means"], prims.scales.amax(-1), view_stack(cams), 0.01)
    assert torch.allclose(bound[1:], NYQUIST * rho[1:] / 30.0)
    before = params["w1"].clone()
    cap.apply(params, 0)
    k = 30.0 * params["w1"].norm(dim=-1)  # eq. (1): every unit's frequency within c · ρ
    over = 30.0 * before.norm(dim=-1) > NYQUIST * rho[:, None]
    over[0] = False  # unseen: unbounded
    assert over.any() and (~over[1:]).any()  # both cases occur
    assert (k[1:] <= NYQUIST * rho[1:, None] * (1 + 1e-5)).all()
    assert torch.allclose(k[over], (NYQUIST * rho[:, None]).expand_as(k)[over], rtol=1e-5)
    assert torch.equal(params["w1"][~over], before[~over])  # rows within the bound untouched
    # directions are kept, and a second application changes nothing
    cos = torch.nn.functional.cosine_similarity(params["w1"], before, dim=-1)
    assert torch.allclose(cos, torch.ones_like(cos))
    once = params["w1"].clone()
    cap.apply(params, 1)
    assert torch.equal(params["w1"], once)
    off = FrequencyCap(cams, factor=0.0, omega0=30.0, near=0.01)
    params["w1"] = before.clone()
    off.apply(params, 0)
    assert torch.equal(params["w1"], before)
    with pytest.raises(ValueError):
        FrequencyCap(cams, factor=-1.0, omega0=30.0, near=0.01)


def test_training_keeps_every_frequency_under_the_bound():
    cams = [camera((3 * math.cos(a), 3 * math.sin(a), 0.4), size=16) for a in (0.0, 1.5, 3.0, 4.5)]
    truth = random_neural(30, extent=0.5, scale=0.2, seed=1)
    with torch.no_grad():
        images = torch.stack([render(truth, c, background=BG).color.clamp(0, 1) for c in cams])
    start = random_neural(30, extent=0.5, scale=0.15, seed=2, omega0=30.0)
    cfg = load_defaults()["train"]
    cfg.update(iterations=8, sh_degree=0, frequency_cap=NYQUIST)
    cfg["densify"].update(start=4, stop=4, every=4)
    state = train(start, cams, images, cfg, background=BG, extent=3.0, seed=0)
    trained = state.primitives()
    rho = footprint(trained.means, trained.scales.amax(-1), view_stack(cams), 0.01)
    k = trained.omega0 * trained.w1.norm(dim=-1)
    assert (k <= NYQUIST * rho[:, None] * (1 + 1e-5)).all()
    # the initial ω0 = 30 frequencies exceed the bound, so the cap acted from the first step
    init = initial_state(start, 0).params
    assert (30.0 * init["w1"].norm(dim=-1) > NYQUIST * footprint(init["means"], start.scales.amax(-1),
                                                                 view_stack(cams), 0.01)[:, None]).any()
    # without it the same run leaves frequencies above the bound
    cfg["frequency_cap"] = 0.0
    free = train(start, cams, images, cfg, background=BG, extent=3.0, seed=0).primitives()
    rho = footprint(free.means, free.scales.amax(-1), view_stack(cams), 0.01)
    assert (free.omega0 * free.w1.norm(dim=-1) > NYQUIST * rho[:, None] * 1.01).any()


def test_the_refresh_interval_divides_densification_and_checkpoints():
    cfg = load_defaults()["train"]
    cap = FrequencyCap.for_training([camera((0.0, -3.0, 0.0))], cfg, omega0=30.0, near=0.01)
    assert cap.every == math.gcd(cfg["densify"]["every"], cfg["checkpoint_every"])
    # the run length plays no part: a short run refreshes as often as a long one
    assert FrequencyCap.for_training([camera((0.0, -3.0, 0.0))], {**cfg, "iterations": 32}, omega0=30.0, near=0.01).every == cap.every
    assert cap.factor == cfg["frequency_cap"]
    cfg = {**cfg, "checkpoint_every": 7}
    assert FrequencyCap.for_training([camera((0.0, -3.0, 0.0))], cfg, omega0=30.0, near=0.01).every == 1
    assert not FrequencyCap.for_training([camera((0.0, -3.0, 0.0))], cfg, omega0=None, near=0.01).enabled
