"""Exact cage deformation (edit/affine.py): SH rotation, similarity invariance, general affine maps
against a quadrature reference of the pulled-back field, identity round trip, inverted tets, splits."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from radfield.core.geometry.cameras import Camera, look_at
from radfield.errors import RadfieldError
from radfield.core.splat.kernels import ALPHA_MAX, ALPHA_MIN
from radfield.core.kinds import random_gaussians, random_neural
from radfield.core.render.rasterize import T_MIN, render
from radfield.core.kinds.neural_density import quadrature_optical_depth
from radfield.core.splat.sh import eval_sh, rotate_sh, sh_to_color
from radfield.edit import affine
from radfield.edit.field import Field, box_cage
from radfield.edit.warp import euler_rotation


def _camera(eye, size=32, target=(0.0, 0.0, 0.0)):
    return Camera(fx=1.2 * size, fy=1.2 * size, cx=size / 2, cy=size / 2, width=size, height=size,
                  c2w=look_at(eye, target))


def _field(kind="neural", n=12, sh_degree=2, seed=0):
    make = random_neural if kind == "neural" else random_gaussians
    prims = make(n, sh_degree=sh_degree, extent=0.5, scale=0.18, seed=seed)
    v, t = box_cage([-1, -1, -1], [1, 1, 1], 2)
    fld = Field(prims, v, t)
    fld.rebind()
    return fld


def test_sh_rotation_matches_rotated_evaluation():
    g = torch.Generator().manual_seed(1)
    coeffs = torch.randn(6, 16, 3, generator=g, dtype=torch.float64)
    rot = torch.tensor(euler_rotation([33.0, -71.0, 128.0]))
    dirs = torch.nn.functional.normalize(torch.randn(6, 3, generator=g, dtype=torch.float64), dim=-1)
    for degree in (1, 2, 3):
        k = (degree + 1) ** 2
        rotated = rotate_sh(coeffs[:, :k], rot)
        # eval at d of the rotated coefficients == eval of the original at Rᵀd (rows: d R = (Rᵀd)ᵀ)
        assert torch.allclose(eval_sh(rotated, dirs, degree), eval_sh(coeffs[:, :k], dirs @ rot, degree), atol=1e-12)
    # per-primitive rotations, and composition R1 R2
    r1, r2 = torch.tensor(euler_rotation([10, 20, 30])), torch.tensor(euler_rotation([-40, 5, 60]))
    both = rotate_sh(rotate_sh(coeffs, r2), r1)
    assert torch.allclose(both, rotate_sh(coeffs, r1 @ r2), atol=1e-12)
    assert not torch.allclose(rotate_sh(coeffs, r1), coeffs, atol=1e-3)


@pytest.mark.parametrize("kind", ["neural", "gaussian"])
def test_similarity_of_the_cage_renders_as_the_pulled_back_camera(kind):
    fld = _field(kind)
    s, rot, t = 1.7, euler_rotation([25.0, -40.0, 70.0]), np.array([0.3, -0.2, 0.5])
    moved = fld.cage_vertices @ (s * rot).T + t
    out = affine.deform_field(fld, moved, gradient="tet")
    out_c = affine.deform_field(fld, moved, gradient="centre")
    cam = _camera(s * np.array([2.2, -1.6, 1.3]) + t, target=t)
    # the same view of the rest field: c2w_rest = T⁻¹ c2w (position (R⁻¹(o − t))/s, rotation Rᵀ R_c)
    c2w = cam.c2w.clone()
    rest = torch.eye(4, dtype=torch.float64)
    rest[:3, :3] = torch.tensor(rot.T) @ c2w[:3, :3]
    rest[:3, 3] = torch.tensor(rot.T @ (c2w[:3, 3].numpy() - t) / s)
    cam_rest = Camera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, rest)
    with torch.no_grad():
        ref = render(fld.prims.to(dtype=torch.float64), cam_rest, background=(0.2, 0.3, 0.4)).color
        for edited in (out, out_c):
            img = render(edited.prims.to(dtype=torch.float64), cam, background=(0.2, 0.3, 0.4)).color
            assert (img - ref).abs().max() < 1e-6
        assert ref.std() > 0.02  # something is in view
    assert out.notes[-1]["split"] == 0


def _pulled_back_reference(rest, a, b, camera, background, preserve_opacity=False, intervals=300):
    """Per-pixel reference of the rest primitives pulled back through x ↦ A x + b: a ray o + ℓd̂ of
    the edited world is the rest ray A⁻¹(o − b) + ℓ A⁻¹d̂; I = (1/max(s')) ∫σ dℓ by quadrature
    in rest space (or the rest-space distance with preserve_opacity); colours from the rest SH at
    R_pᵀ d (R_p the polar rotation of A). Sorted by the edited centres' depths."""
    rest = rest.to(dtype=torch.float64)
    a_t, b_t = torch.tensor(a), torch.tensor(b)
    a_inv = torch.linalg.inv(a_t)
    rot = torch.tensor(affine.polar_rotation(a))
    smax = torch.exp(rest.log_scales).amax(-1)
    mu_new = rest.means @ a_t.T + b_t
    c2w = camera.c2w
    o = c2w[:3, 3]
    depth = (mu_new - o) @ c2w[:3, 2]
    order = torch.argsort(depth).tolist()
    from radfield.core.kinds import quat_to_rotmat
    rs = a_t @ quat_to_rotmat(rest.quats) * torch.exp(rest.log_scales)[:, None, :]
    smax_new = torch.linalg.svdvals(rs).amax(-1)
    colors = sh_to_color(rest.sh, torch.nn.functional.normalize(mu_new - o, dim=-1) @ rot, rest.sh_degree)
    img = torch.zeros(camera.height, camera.width, 3, dtype=torch.float64)
    o_rest = a_inv @ (o - b_t)
    for row in range(camera.height):
        for col in range(camera.width):
            d_cam = torch.tensor([(col + 0.5 - camera.cx) / camera.fx, (row + 0.5 - camera.cy) / camera.fy, 1.0], dtype=torch.float64)
            d = c2w[:3, :3] @ (d_cam / d_cam.norm())
            e = a_inv @ d
            trans, pix = 1.0, torch.zeros(3, dtype=torch.float64)
            for i in order:
                q = quadrature_optical_depth(rest, i, o_rest, e, l_min=0.01 * d_cam.norm().item() * e.norm().item(),
                                             scan=801, intervals=intervals)
                depth_i = q if preserve_opacity else q * smax[i].item() / (smax_new[i].item() * e.norm().item())
                alpha = min(ALPHA_MAX, 1.0 - math.exp(-max(0.0, depth_i)))
                if alpha < ALPHA_MIN:
                    continue
                if trans * (1 - alpha) < T_MIN:
                    break
                pix += trans * alpha * colors[i]
                trans *= 1 - alpha
            img[row, col] = pix + trans * torch.tensor(background, dtype=torch.float64)
    return img


def test_general_affine_cage_map_matches_the_pulled_back_quadrature():
    fld = _field("neural", n=5, sh_degree=1, seed=3)
    a = euler_rotation([20.0, 35.0, -15.0]) @ np.array([[1.4, 0.3, 0.0], [0.0, 0.8, 0.25], [0.1, 0.0, 1.15]])
    b = np.array([0.1, 0.2, -0.1])
    # the density convention (preserve_opacity off; the default takes it on for such a map)
    out = affine.deform_field(fld, fld.cage_vertices @ a.T + b, preserve_opacity=False)
    assert out.prims.rest_metric is None
    assert affine.deform_field(fld, fld.cage_vertices @ a.T + b).prims.rest_metric is not None
    cam = _camera([2.5, -2.0, 1.5], size=12)
    bg = (1.0, 1.0, 1.0)
    with torch.no_grad():
        fast = render(out.prims.to(dtype=torch.float64), cam, background=bg).color
    ref = _pulled_back_reference(fld.prims, a, b, cam, bg)
    assert (ref - 1.0).abs().max() > 0.05   # primitives are visible
    assert (fast - ref).abs().max() < 2e-3

    # preserve_opacity: exact on each primitive's central ray; measure the whole image's error
    kept = affine.deform_field(fld, fld.cage_vertices @ a.T + b, preserve_opacity=True)
    assert kept.prims.rest_metric is not None
    with torch.no_grad():
        fast_kept = render(kept.prims.to(dtype=torch.float64), cam, background=bg).color
    ref_kept = _pulled_back_reference(fld.prims, a, b, cam, bg, preserve_opacity=True)
    err = (fast_kept - ref_kept).abs().max().item()
    print(f"preserve_opacity central-ray approximation: max abs pixel error {err:.4f} "
          f"(the plain affine map's difference from it: {(fast - ref_kept).abs().max().item():.4f})")
    assert err < 0.6 * (fast - ref_kept).abs().max().item()


def test_identity_cage_keeps_the_model_bit_identical():
    for kind in ("neural", "gaussian"):
        fld = _field(kind)
        out = affine.deform_field(fld, fld.cage_vertices.copy())
        for name, value in fld.prims.tensors().items():
            assert torch.equal(value, out.prims.tensors()[name]), name
        assert out.notes[-1]["moved_primitives"] == 0


@pytest.mark.parametrize("gradient", ["tet", "centre", "smooth"])
def test_local_edit_leaves_far_primitives_untouched(gradient):
    # "smooth" fits each vertex's gradient over its neighbourhood (up to two rings at the cage's
    # boundary), so its reach is wider than the tet maps': a 4³ cage leaves room for far primitives
    fld = _field("neural", n=30)
    if gradient == "smooth":
        v, t = box_cage([-1, -1, -1], [1, 1, 1], 4)
        fld = Field(random_neural(60, extent=0.9, scale=0.1, seed=2), v, t)
        fld.rebind()
    moved = fld.cage_vertices.copy()
    corner = np.flatnonzero((moved > 0.99).all(1))
    moved[corner] += 0.2
    out = affine.deform_field(fld, moved, split=None, gradient=gradient)
    same = (fld.prims.means == out.prims.means).all(1)
    assert 0 < int(same.sum()) < len(fld.prims)
    if gradient != "centre":   # (centre's A is interpolated from vertex gradients beyond μ's tet)
        for name, value in fld.prims.tensors().items():    # the far ones keep every parameter
            assert torch.equal(value[same], out.prims.tensors()[name][same]), name


def test_inverted_and_degenerate_tets_are_one_line_errors():
    fld = _field("neural")
    moved = fld.cage_vertices.copy()
    centre = np.flatnonzero(np.abs(moved).sum(1) == 0)[0]
    moved[centre] = [1.5, 1.5, 1.5]   # the centre vertex pushed through a corner: tets turn inside out
    with pytest.raises(RadfieldError, match=r"inverted tets in the deformed cage .*: \d+") as info:
        affine.deform_field(fld, moved)
    assert "\n" not in str(info.value)
    flat = fld.cage_vertices.copy()
    flat[:, 2] = 0.0
    with pytest.raises(RadfieldError, match="tets in the deformed cage"):
        affine.deform_field(fld, flat)


def test_twist_splits_straddling_primitives_and_stays_finite():
    fld = _field("neural", n=40)
    v = fld.cage_vertices
    theta = np.radians(60.0) * v[:, 2]
    c, s = np.cos(theta), np.sin(theta)
    twisted = np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]], 1)
    out = affine.deform_field(fld, twisted, split=0.2)
    note = out.notes[-1]
    assert note["split"] > 0 and len(out.prims) == len(fld.prims) + note["split"]
    for value in out.prims.tensors().values():
        assert torch.isfinite(value).all()


def test_split_keeps_the_density_inside_each_half():
    prims = random_neural(3, extent=0.3, scale=0.2, seed=5).to(dtype=torch.float64)
    halves = affine.split_primitives(prims, np.array([1]))
    from radfield.core.kinds.neural_density import primitive_density
    # child i (rows 2 and 3 hold the halves of primitive 1): same density at points inside it
    for child in (2, 3):
        mu, s = halves.means[child], torch.exp(halves.log_scales[child])
        from radfield.core.kinds import quat_to_rotmat
        rot = quat_to_rotmat(halves.quats[child][None])[0]
        z = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1) * torch.rand(50, 1, dtype=torch.float64) * 0.9
        x = mu + (z * s) @ rot.T
        # optical-depth density per unit of the primitive's own size: σ/max(s) is what is conserved
        child_sigma = primitive_density(halves, child, x) / s.max()
        parent_sigma = primitive_density(prims, 1, x) / torch.exp(prims.log_scales[1]).max()
        inside_parent = primitive_density(prims.map(lambda t: t), 1, x) != 0
        assert torch.allclose(child_sigma[inside_parent], parent_sigma[inside_parent], atol=1e-10)
