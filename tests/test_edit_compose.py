"""Composition and SH rotation (radfield.edit.compose), through parse_spec + apply_operations."""

import numpy as np
import pytest
import torch

from radfield.core.geometry.cameras import Camera, look_at
from radfield.errors import RadfieldError
from radfield.core.kinds import random_gaussians, random_neural
from radfield.core.render.rasterize import render
from radfield.core.splat.sh import eval_sh
from radfield.core.splat.sh import rotate_sh
from radfield.edit.compose import concat_prims
from radfield.edit.warp import euler_rotation
from radfield.edit.field import Field
from radfield.edit.spec import EditContext, apply_operations, parse_spec


def camera(eye=(0.0, -4.0, 0.0), size=32):
    return Camera(fx=1.4 * size, fy=1.4 * size, cx=size / 2, cy=size / 2, width=size, height=size, c2w=look_at(eye, (0, 0, 0)))


def compose(fld, other, tmp_path, **args):
    (tmp_path / "other.safetensors").write_bytes(b"")
    ops = parse_spec({"operations": [{"compose": {"model": "other.safetensors", **args}}]})
    return apply_operations(fld, ops, EditContext(base_dir=tmp_path, load_operand=lambda path: other))


def test_rotate_sh_turns_the_colour_function():
    rot = euler_rotation([30, -20, 75])
    sh = torch.randn(5, 16, 3, dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.randn(5, 3, dtype=torch.float64), dim=-1)
    # f'(d) = f(Rᵀ d)
    assert torch.allclose(eval_sh(rotate_sh(sh, rot), d, 3), eval_sh(sh, d @ torch.as_tensor(rot), 3), atol=1e-12)
    assert np.allclose(euler_rotation([0, 0, 90]) @ [1, 0, 0], [0, 1, 0])


def test_compose_with_itself_equals_depth_compositing(tmp_path):
    prims = random_neural(15, sh_degree=2, extent=0.3, scale=0.1, b2=2.0, seed=1).to(dtype=torch.float64)
    fld = Field(prims)
    # the copy: turned, scaled and moved behind the original (farther along +y) and half beside it
    out = compose(fld, Field(prims), tmp_path, rotate=[10, 20, 40], translate=[0.35, 2.0, 0.1], scale=1.2)
    assert len(out.prims) == 2 * len(prims)
    for name, tensor in prims.tensors().items():
        assert torch.equal(getattr(out.prims, name)[: len(prims)], tensor)
    copy = out.prims.select(torch.arange(len(prims), 2 * len(prims)))
    cam = camera()
    front = render(prims, cam, background=(0.0, 0.0, 0.0))
    back = render(copy, cam)
    composited = front.color + (1 - front.alpha)[..., None] * back.color
    # up to early termination: a pixel stops before a splat that would take T below 1e-4 (here one
    # pixel with T = 2e-3 before an α = 0.99 splat of the back part: a 4e-4 difference)
    diff = (render(out.prims, cam).color - composited).abs().max(-1).values
    assert diff.max() < 1e-3 and (diff > 1e-9).sum() <= 2
    # and the copy is the original seen from the correspondingly moved camera
    rot, s, t = torch.as_tensor(euler_rotation([10, 20, 40])), 1.2, torch.tensor([0.35, 2.0, 0.1], dtype=torch.float64)
    c2w = cam.c2w.clone()
    c2w[:3, :3], c2w[:3, 3] = rot @ c2w[:3, :3], s * rot @ c2w[:3, 3] + t
    moved = Camera(fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy, width=cam.width, height=cam.height, c2w=c2w)
    assert torch.allclose(render(copy, moved, near=0.012).color, render(prims, cam).color, atol=1e-9)


def test_cages_merge_as_disjoint_union(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) - 0.25
    t = np.array([[0, 1, 2, 3]])
    prims = random_neural(6, extent=0.05, scale=0.03, seed=2).to(dtype=torch.float64)
    fld = Field(prims, v, t)
    fld.rebind()
    out = compose(fld, Field(prims, v, t, fld.tet.copy(), fld.bary.copy()), tmp_path, translate=[2, 0, 0])
    assert out.cage_vertices.shape == (8, 3) and out.cage_tets.tolist() == [[0, 1, 2, 3], [4, 5, 6, 7]]
    assert out.tet.tolist() == [0] * 6 + [1] * 6
    centres = np.einsum("pk,pkd->pd", out.bary, out.cage_vertices[out.cage_tets[out.tet]])
    assert np.allclose(centres, out.prims.means.numpy(), atol=1e-12)


def test_padding_sh_hidden_and_omega0_keep_renders():
    a = random_neural(8, sh_degree=2, hidden=8, omega0=30.0, extent=0.3, scale=0.15, seed=3).to(dtype=torch.float64)
    b = random_neural(8, sh_degree=0, hidden=4, omega0=20.0, extent=0.3, scale=0.15, seed=4).to(dtype=torch.float64)
    b.means = b.means + torch.tensor([0.0, 3.0, 0.0], dtype=torch.float64)      # far behind a
    both = concat_prims(a, b)
    assert both.sh.shape[1] == 9 and both.hidden == 8 and both.omega0 == 30.0
    padded_b = both.select(torch.arange(8, 16))
    cam = camera()
    assert torch.allclose(render(padded_b, cam).color, render(b, cam).color, atol=1e-9)


def test_bad_compose_entries_are_one_line(tmp_path):
    prims = random_neural(4, seed=5)
    with pytest.raises(RadfieldError, match=r"^operations\[0\]\.compose\.model: required"):
        apply_operations(Field(prims), parse_spec({"operations": [{"compose": {"scale": 2}}]}), EditContext(base_dir=tmp_path))
    with pytest.raises(RadfieldError, match=r"^operations\[0\]\.compose: cannot combine a neural model with a gaussian"):
        compose(Field(prims), Field(random_gaussians(3)), tmp_path)
    with pytest.raises(RadfieldError, match=r"^operations\[0\]\.compose\.scale: must be positive"):
        compose(Field(prims), Field(prims), tmp_path, scale=-1)
