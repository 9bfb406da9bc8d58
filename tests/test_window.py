"""The density window 1.5 (1 − r²) (prims.window) at every place that evaluates a neural
primitive's density: the closed form against the quadrature reference, the renderer against the
per-pixel reference, and each point site against a brute-force evaluation (windowed = hard-edged
× the window; window off = the hard-edged density, unchanged)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
import yaml

from radfield.delivery.bake import prune, to_fp16_and_back
from radfield.core.geometry.cameras import Camera, look_at
from radfield.errors import RadfieldError
from radfield.model_file import load_model, save_model
from radfield.core.splat.kernels import alpha_from_optical_depth
from radfield.core.kinds.neural_density import neural_line_integral
from radfield.core.kinds.moment_matching import gaussians_from_neural, neural_density_samples
from radfield.core.kinds.neural_density import ellipsoid_radius_sq
from radfield.core.kinds import quat_to_rotmat, random_neural
from radfield.core.render.rasterize import render
from radfield.core.kinds.neural_density import primitive_density, quadrature_optical_depth
from radfield.core.render.reference import reference_render
from radfield.core.kinds import neural_density
from radfield.edit import boolean, retrain
from radfield.edit.compose import concat_prims
from radfield.edit.affine import map_primitives, split_primitives
from radfield.edit.field import Field
from radfield.edit.recolor import peak_density
from radfield.edit.spec import EditContext, apply_operations, parse_spec


def windowed(prims):
    return replace(prims, window=True)


# --- brute force: each primitive on its own, from its matrices --------------------------------

def brute_r2(prims, x: torch.Tensor) -> torch.Tensor:
    """|(R S)⁻¹(x − μ)|² (Q, P) of points x (Q, 3), one primitive at a time by a linear solve."""
    cols = []
    for i in range(len(prims)):
        rs = quat_to_rotmat(prims.quats[i][None])[0] @ torch.diag(prims.log_scales[i].exp())
        local = torch.linalg.solve(rs, (x - prims.means[i]).T).T
        cols.append((local * local).sum(-1))
    return torch.stack(cols, 1)


def brute_sigma(prims, x: torch.Tensor) -> torch.Tensor:
    """The hard-edged cos-MLP σ_i(x) (Q, P), no ellipsoid test (paper eq. 5-6, term by term)."""
    cols = []
    for i in range(len(prims)):
        u = (x - prims.means[i]) / prims.log_scales[i].exp().max()
        terms = [prims.w2[i, k] * torch.cos(prims.omega0 * (u @ prims.w1[i, k] + prims.b1[i, k])) for k in range(prims.hidden)]
        cols.append(sum(terms) + prims.b2[i])
    return torch.stack(cols, 1)


def brute_window(prims, x):
    return 1.5 * (1 - brute_r2(prims, x))


def scene64(n=5, seed=0, **kwargs):
    args = dict(scale=0.3, extent=0.4, w2_amplitude=0.5, b2=1.0, seed=seed)
    return random_neural(n, **{**args, **kwargs}).to(dtype=torch.float64)


def points_around(prims, n=400, seed=0):
    """Points in and around the primitives (about half inside some ellipsoid)."""
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * 0.7


def test_ellipsoid_radius_sq_is_the_unit_sphere_radius():
    prims = scene64()
    x = points_around(prims)
    r2 = ellipsoid_radius_sq(prims.means, prims.log_scales, prims.quats, x[:, None])
    torch.testing.assert_close(r2, brute_r2(prims, x), rtol=1e-12, atol=1e-12)
    ends = neural_density.ellipsoid_points(prims, torch.eye(3, dtype=torch.float64))          # μ + R S e_k
    r2_ends = ellipsoid_radius_sq(prims.means[:, None], prims.log_scales[:, None], prims.quats[:, None], ends)
    torch.testing.assert_close(r2_ends, torch.ones(len(prims), 3, dtype=torch.float64))


# --- the closed form and the renderer against the references ---------------------------------

def rays_through(prims, i, g):
    """(origin, direction, l_min) through primitive i: through the centre, at half the
    silhouette's reach, grazing (0.999 of it), from a camera inside it, and with a near plane
    that cuts the chord at its middle."""
    mu, s = prims.means[i], prims.log_scales[i].exp()
    m = (quat_to_rotmat(prims.quats[i][None])[0] / s).T                      # S⁻¹Rᵀ
    rays = []
    for _ in range(2):
        d = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=torch.float64), dim=0)
        e = torch.nn.functional.normalize(torch.linalg.cross(d, torch.randn(3, generator=g, dtype=torch.float64)), dim=0)
        me, md = m @ e, m @ d
        reach = 1 / torch.sqrt(me @ me - (me @ md) ** 2 / (md @ md))         # the silhouette along e
        far = 3 * float(s.max())
        for f in (0.0, 0.5, 0.999):
            rays.append((mu + f * reach * e - far * d, d, 0.0))
        inside = mu + quat_to_rotmat(prims.quats[i][None])[0] @ (0.6 * s * torch.nn.functional.normalize(
            torch.randn(3, generator=g, dtype=torch.float64), dim=0))
        rays.append((inside, d, 0.0))                                       # camera inside
        rays.append((mu - far * d, d, far))                                # near plane through μ
    return rays


@pytest.mark.parametrize("seed", [0, 1])
def test_windowed_closed_form_matches_quadrature(seed):
    g = torch.Generator().manual_seed(seed)
    prims = windowed(scene64(3, seed=seed, w2_amplitude=1.0, b2=0.3))
    for i in range(len(prims)):
        one = prims.select([i])
        for origin, direction, l_min in rays_through(prims, i, g):
            fast = neural_line_integral(one, origin[None], direction[None], torch.tensor([l_min], dtype=torch.float64))
            slow = quadrature_optical_depth(prims, i, origin, direction, l_min=l_min)
            assert fast.item() == pytest.approx(slow, rel=1e-6, abs=1e-10), (i, origin, direction, l_min)
    # the window matters: a central chord of the hard-edged primitive integrates another density
    origin, direction, _ = rays_through(prims, 0, g)[0]
    hard = quadrature_optical_depth(replace(prims, window=False), 0, origin, direction)
    assert abs(hard - quadrature_optical_depth(prims, 0, origin, direction)) > 1e-3


def tiny_camera(eye=(0.3, -3.0, 0.5)):
    return Camera(fx=10.0, fy=11.0, cx=4.2, cy=3.4, width=8, height=7, c2w=look_at(eye, (0, 0, 0)))


def test_windowed_render_matches_reference_render():
    prims = random_neural(6, sh_degree=1, scale=0.35, extent=0.6, b2=2.0, seed=1)
    eye = torch.tensor([0.3, -3.0, 0.5])
    prims.means[0], prims.log_scales[0], prims.b2[0] = eye + torch.tensor([0.05, 0.1, -0.05]), math.log(0.4), 0.3
    prims = windowed(prims.to(dtype=torch.float64))                             # the camera inside primitive 0
    cam = tiny_camera(tuple(eye.tolist()))
    fast = render(prims, cam, background=(0.2, 0.3, 0.4), near=0.05)
    slow = reference_render(prims, cam, background=(0.2, 0.3, 0.4), near=0.05)
    assert fast.meta["contributing_pairs"] > 20
    assert (fast.color - slow).abs().max() < 1e-6
    hard = render(replace(prims, window=False), cam, background=(0.2, 0.3, 0.4), near=0.05)
    assert (hard.color - fast.color).abs().max() > 1e-2


# --- densities at points -----------------------------------------------------------------------

def test_reference_density_is_the_windowed_one():
    prims = scene64()
    x = points_around(prims)
    inside = brute_r2(prims, x) <= 1
    expected_hard = torch.where(inside, brute_sigma(prims, x), 0.0)
    for i in range(len(prims)):
        torch.testing.assert_close(primitive_density(prims, i, x), expected_hard[:, i])
        torch.testing.assert_close(primitive_density(windowed(prims), i, x), expected_hard[:, i] * brute_window(prims, x)[:, i])


def test_retrain_point_densities_are_windowed():
    prims = scene64()
    x = points_around(prims)
    r2, sigma, smax = brute_r2(prims, x), brute_sigma(prims, x), prims.log_scales.exp().amax(-1)
    hard = torch.where(r2 <= 1, sigma / smax, 0.0)
    soft = hard * brute_window(prims, x)
    assert (soft - hard).abs().max() > 0.1
    torch.testing.assert_close(neural_density.pair_density(prims, x), hard)
    torch.testing.assert_close(neural_density.pair_density(windowed(prims), x), soft)
    # one point per primitive, and the field's D(x) = Σ max(σ, 0)/max s over the primitives
    q = torch.arange(len(x)) % len(prims)
    one = prims.select(q)
    torch.testing.assert_close(neural_density._pair_density_1to1(one, x), hard[torch.arange(len(x)), q])
    torch.testing.assert_close(neural_density._pair_density_1to1(windowed(one), x), soft[torch.arange(len(x)), q])
    np.testing.assert_allclose(neural_density.field_density(prims, x), hard.clamp_min(0).sum(1).numpy(), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(neural_density.field_density(windowed(prims), x), soft.clamp_min(0).sum(1).numpy(), rtol=1e-10, atol=1e-12)
    # each primitive at its own points (no ellipsoid test)
    own = neural_density.ellipsoid_points(prims, neural_density.unit_ball_samples(20))
    diag = lambda f: torch.stack([f(own[i])[:, i] for i in range(len(prims))])
    torch.testing.assert_close(neural_density.neural_sigma(prims, own), diag(lambda y: brute_sigma(prims, y)))
    torch.testing.assert_close(neural_density.neural_sigma(windowed(prims), own),
                               diag(lambda y: brute_sigma(prims, y) * brute_window(prims, y)))


def test_peak_density_is_windowed():
    prims = scene64()
    u = neural_density.unit_ball_samples(128)
    own = neural_density.ellipsoid_points(prims, u)
    sigma = torch.stack([brute_sigma(prims, own[i])[:, i] for i in range(len(prims))])     # (P, S)
    torch.testing.assert_close(peak_density(prims), sigma.max(1).values)
    torch.testing.assert_close(peak_density(windowed(prims)), (sigma * 1.5 * (1 - (u * u).sum(-1))).max(1).values)


def test_moment_samples_are_windowed():
    prims = scene64(4)
    x, mass, total, _ = neural_density_samples(prims)
    x_w, mass_w, total_w, _ = neural_density_samples(windowed(prims))
    torch.testing.assert_close(x_w, x)
    factor = torch.stack([brute_window(prims, x[i])[:, i] for i in range(len(prims))])       # (P, N)
    signed = torch.stack([brute_sigma(prims, x[i])[:, i] for i in range(len(prims))])
    cell = (2.0 / 14) ** 3 * prims.log_scales.exp().prod(-1)[:, None] / prims.log_scales.exp().amax(-1)[:, None]
    torch.testing.assert_close(mass, (signed * cell).clamp_min(0))
    torch.testing.assert_close(mass_w, (signed * factor * cell).clamp_min(0))
    torch.testing.assert_close(total_w, (signed * factor * cell).sum(-1).clamp_min(0))
    # the exported Gaussians follow: the window moves mass to the centre (smaller covariance)
    g, g_w = gaussians_from_neural(prims), gaussians_from_neural(windowed(prims))
    assert (g_w.log_scales.sum(-1) < g.log_scales.sum(-1)).all()


# --- retraining and boolean operations ---------------------------------------------------------

def test_teacher_windowed_closed_form_and_masked_quadrature():
    prims = windowed(scene64(4, seed=4, scale=0.25, extent=0.2, b2=2.0, sh_degree=1))
    cam = Camera(fx=14, fy=14, cx=5, cy=5, width=10, height=10, c2w=look_at((0.4, -3.0, 0.7), (0, 0, 0)))
    plain = retrain.teacher_render(prims, cam)
    assert torch.allclose(plain, render(prims, cam).color, atol=1e-9)
    assert (plain - render(replace(prims, window=False), cam).color).abs().max() > 1e-2
    # a mask that keeps everything: the midpoint rule of the windowed σ (neural_sigma)
    everything = lambda p: np.ones(len(p), bool)
    masked = retrain.teacher_render(prims, cam, np.zeros(len(prims), int), [everything], samples=256)
    assert (masked - plain).abs().max() < 1e-4
    # opacity along rays leaving points: 1 − Π(1 − α) of the windowed closed form too
    faint = replace(prims, b2=prims.b2 * 0.2, w2=prims.w2 * 0.2)
    origins = torch.tensor([[0.0, -2.0, 0.0], [0.05, -2.0, 0.1]], dtype=torch.float64)
    dirs = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    depth = neural_line_integral(faint, origins, dirs, torch.zeros(2, dtype=torch.float64))
    alpha = alpha_from_optical_depth(depth)
    expected = 1 - (1 - alpha).prod(1)
    assert ((alpha > 0).sum(1) >= 2).all() and (expected < 0.9).all()
    np.testing.assert_allclose(retrain.opacity_from(faint, origins.numpy(), dirs.numpy()), expected.numpy(), rtol=1e-9)


def test_stage1_student_density_is_the_windowed_pair_density():
    student = scene64(4, seed=6).to(dtype=torch.float32)
    pts = neural_density.ellipsoid_points(student, neural_density.unit_ball_samples(30, 1)).reshape(-1, 3)
    params = {n: t for n, t in student.tensors().items()}
    q_idx, p_idx = retrain._inside_pairs(student, pts)
    smax = student.scales.amax(-1)
    for prims in (student, windowed(student)):
        window = retrain._pair_window(prims, pts, q_idx, p_idx)
        density = retrain.stage1_density(params, prims.omega0, pts, q_idx, p_idx, smax, window)
        expected = neural_density.pair_density(prims, pts).sum(1)     # float32: the same inside test
        torch.testing.assert_close(density, expected, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("best", ["stage1", "stage2"])
def test_retrained_primitives_keep_the_window(monkeypatch, best):
    prims = windowed(scene64(6, seed=7, scale=0.2, extent=0.2, sh_degree=0)).to(dtype=torch.float32)
    frozen, student = prims.select(torch.arange(3)), prims.select(torch.arange(3, 6))
    pts = neural_density.ellipsoid_points(student, neural_density.unit_ball_samples(10)).reshape(-1, 3)
    cam = retrain.orbit_around(student, np.arange(3), 1, 8)
    scores = iter({"stage1": [0.0, 2.0, 1.0], "stage2": [0.0, 1.0, 2.0]}[best])   # PSNR before, stage 1, stage 2
    monkeypatch.setattr(retrain, "_mean_psnr", lambda *args: next(scores))
    fitted, figures = retrain.retrain(frozen, student, pts, torch.zeros(len(pts)), cam, [torch.ones(8, 8, 3)],
                                      steps1=2, steps2=2)
    assert figures["best_stage"] == best and fitted.window
    with pytest.raises(ValueError, match="different density windows"):
        retrain.retrain(replace(frozen, window=False), student, pts, torch.zeros(len(pts)), cam, [torch.ones(8, 8, 3)])


def test_boolean_density_teacher_and_caps_are_windowed():
    student = windowed(scene64(4, seed=9))
    keep_all = [lambda p: np.ones(len(p), bool)]
    pts, target = boolean.density_teacher(student, 4, np.zeros(4, int), keep_all, seed=0, per_prim=12)
    r2, sigma = brute_r2(student, pts), brute_sigma(student, pts)
    expected = torch.where(r2 <= 1, sigma * 1.5 * (1 - r2) / student.log_scales.exp().amax(-1), 0.0).sum(1)
    torch.testing.assert_close(target, expected)
    # the cap discs of a windowed solid are windowed
    ball = windowed(random_neural(1, scale=1.0, b2=20.0, w2_amplitude=0.0, seed=1).to(dtype=torch.float64))
    ball.means[:] = 0.0
    ball.log_scales[:] = 0.0
    caps = boolean.cap_primitives(ball, np.zeros((2, 3)) + [[0.1, 0, 0], [-0.1, 0, 0]], np.tile([0.0, 0, 1], (2, 1)), 0.1)
    assert len(caps) == 2 and caps.window


# --- geometry edits, composition, files ---------------------------------------------------------

def test_deformation_maps_the_windowed_density_exactly():
    prims = windowed(scene64(3, seed=10))
    g = torch.Generator().manual_seed(3)
    a = (torch.eye(3, dtype=torch.float64) + 0.3 * torch.randn(3, 3, generator=g, dtype=torch.float64)).numpy()
    b = np.array([0.2, -0.1, 0.3])
    moved = map_primitives(prims, a, prims.means.numpy() @ a.T + b)
    assert moved.window
    x = points_around(prims, 200)
    for i in range(len(prims)):
        torch.testing.assert_close(primitive_density(moved, i, x @ torch.as_tensor(a).T + torch.as_tensor(b)),
                                   primitive_density(prims, i, x), atol=1e-9, rtol=1e-9)
    assert split_primitives(prims, np.array([0])).window


def test_composing_fields_with_different_windows_is_refused(tmp_path):
    hard, soft = random_neural(3, seed=1), windowed(random_neural(3, seed=2))
    (tmp_path / "other.safetensors").write_bytes(b"")
    ops = parse_spec({"operations": [{"compose": {"model": "other.safetensors"}}]})
    with pytest.raises(RadfieldError, match=r"^operations\[0\]\.compose: cannot combine a hard-edged neural model "
                                            r"\(window=0\) with a windowed one \(window=1\)") as info:
        apply_operations(Field(hard), ops, EditContext(base_dir=tmp_path, load_operand=lambda path: Field(soft)))
    assert "\n" not in str(info.value)
    with pytest.raises(RadfieldError, match=r"^boolean: cannot combine a windowed neural model \(window=1\) with a hard-edged"):
        concat_prims(soft, hard, "boolean")                                 # the library path (merge_fields)
    both = apply_operations(Field(soft), ops, EditContext(base_dir=tmp_path, load_operand=lambda path: Field(soft)))
    assert both.prims.window and len(both.prims) == 6


def test_edit_cli_refuses_mixed_windows_in_one_line(cli, tmp_path):
    save_model(tmp_path / "soft.safetensors", windowed(random_neural(3, seed=1)))
    save_model(tmp_path / "hard.safetensors", random_neural(3, seed=2))
    spec = tmp_path / "edit.yaml"
    spec.write_text(yaml.safe_dump({"operations": [{"compose": {"model": "hard.safetensors"}}]}))
    code, _, err = cli("edit", tmp_path / "soft.safetensors", "--spec", spec, "-o", tmp_path / "out")
    assert code == 1 and err.startswith("radfield: error: ") and err.count("\n") == 1, err
    assert "window=1" in err and "window=0" in err and not (tmp_path / "out").exists()
    code, _, err = cli("edit", tmp_path / "soft.safetensors", "-o", tmp_path / "moved", "--translate", "0,0,1", "-q")
    assert code == 0, err
    assert load_model(tmp_path / "moved" / "edit" / "model.safetensors").window


def test_model_file_and_bake_keep_the_window(tmp_path):
    prims = windowed(random_neural(4, seed=3))
    save_model(tmp_path / "m.safetensors", prims)
    assert load_model(tmp_path / "m.safetensors").window
    kept, _ = prune(prims, torch.tensor([1.0, 0.0, 1.0, 1.0]))
    baked = to_fp16_and_back(kept)
    assert len(baked) == 3 and baked.window
    save_model(tmp_path / "b.safetensors", baked, dtype=torch.float16)
    assert load_model(tmp_path / "b.safetensors").window
    save_model(tmp_path / "h.safetensors", replace(prims, window=False))
    assert not load_model(tmp_path / "h.safetensors").window


@pytest.mark.parametrize("op", [
    {"remesh": {"select": {"sphere": {"center": [0.4, 0.4, 0.4], "radius": 0.6}}, "edge_length": 0.3, "split": True,
                "steps": 3, "views": 2, "size": 12}},
    {"boolean": {"op": "difference", "shape": {"halfspace": {"point": [0.05, 0, 0], "normal": [1, 0.3, 0]}},
                 "steps": 3, "views": 2, "size": 12}},
])
def test_retraining_edits_of_a_windowed_field_stay_windowed(op):
    """remesh with split and a boolean cut retrain against the windowed teacher and return a
    windowed field (concat_prims would refuse a hard-edged fitted part)."""
    from radfield.edit.field import box_cage
    prims = windowed(random_neural(24, sh_degree=0, extent=0.7, scale=0.18, b2=2.0, seed=5))
    v, t = box_cage([-1, -1, -1], [1, 1, 1], 1)
    fld = Field(prims, v, t)
    fld.rebind()
    out = apply_operations(fld, parse_spec({"operations": [op]}), EditContext())
    note = out.notes[-1]
    assert note.get("retrained", 0) > 0 and out.prims.window
