"""Remeshing a region of the cage (radfield.edit.remesh): conforming bisection, re-binding."""

import numpy as np
import pytest
import torch

from radfield.core.geometry.cage import tet_volumes
from radfield.core.geometry.cameras import Camera, look_at
from radfield.errors import RadfieldError
from radfield.core.train.losses import psnr
from radfield.core.kinds import random_neural
from radfield.core.render.rasterize import render
from radfield.edit.field import Field
from radfield.edit.remesh import _EDGES, oversized
from radfield.edit.spec import EditContext, apply_operations, parse_spec


def cube_cage():
    """The unit cube [-1, 1]^3 as 6 positively oriented tets (Kuhn subdivision)."""
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * 2 - 1
    idx = lambda x, y, z: 4 * x + 2 * y + z
    tets = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        p = [0, 0, 0]
        path = [idx(*p)]
        for axis in perm:
            p[axis] = 1
            path.append(idx(*p))
        tets.append(path)
    tets = np.array(tets)
    flip = tet_volumes(v, tets) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return v, tets


def faces(t):
    f = np.sort(np.concatenate([t[:, [1, 2, 3]], t[:, [0, 2, 3]], t[:, [0, 1, 3]], t[:, [0, 1, 2]]]), axis=1)
    _, counts = np.unique(f, axis=0, return_counts=True)
    return counts


def remeshed(prims, centre, **args):
    """The field of prims in the cube cage, remeshed in a sphere of radius 0.6 around centre to edge 0.3."""
    v, t = cube_cage()
    fld = Field(prims, v, t)
    fld.rebind()
    region = {"sphere": {"center": centre, "radius": 0.6}}
    out = apply_operations(fld, parse_spec({"operations": [{"remesh": {"select": region, "edge_length": 0.3, **args}}]}),
                           EditContext())
    return out, out.notes[-1], v, t


def test_remesh_refines_the_region_conformingly_and_renders_identically():
    prims = random_neural(30, sh_degree=1, extent=0.8, scale=0.1, b2=2.0, seed=1)
    out, note, v, t = remeshed(prims, [0.5, 0.5, 0.5])
    nv, nt = out.cage_vertices, out.cage_tets
    assert note["tets_before"] == 6 and note["tets_after"] == len(nt) > 100
    vol = tet_volumes(nv, nt)
    assert (vol > 0).all() and np.isclose(vol.sum(), 8.0)               # same solid, all positive
    assert set(faces(nt).tolist()) <= {1, 2}                             # conforming: a face is shared by ≤ 2 tets
    assert (faces(nt) == 1).sum() * 1.0 > 0 and np.isclose(_boundary_area(nv, nt), 24.0)
    e = np.sort(nt[:, _EDGES], axis=2).reshape(-1, 2)
    mid = (nv[e[:, 0]] + nv[e[:, 1]]) / 2
    inside = np.linalg.norm(mid - 0.5, axis=1) <= 0.6
    assert np.linalg.norm(nv[e[inside, 1]] - nv[e[inside, 0]], axis=1).max() <= 0.3
    assert np.linalg.norm(nv[e[~inside, 1]] - nv[e[~inside, 0]], axis=1).max() > 0.3   # refined only there
    # the primitives are untouched; an undeformed (identity) cage maps every centre to itself
    for name, tensor in prims.tensors().items():
        assert torch.equal(getattr(out.prims, name), tensor)
    centres = np.einsum("pk,pkd->pd", out.bary, nv[nt[out.tet]])
    assert np.allclose(centres, prims.means.double().numpy(), atol=1e-6)
    cam = Camera(fx=40.0, fy=40.0, cx=16, cy=16, width=32, height=32, c2w=look_at((0.5, -3, 0.8), (0, 0, 0)))
    identity = out.prims.map(lambda x: x.clone())
    identity.means = torch.as_tensor(centres, dtype=prims.means.dtype)
    assert torch.allclose(render(identity, cam).color, render(prims, cam).color, atol=1e-5)


def _boundary_area(v, t):
    f = np.sort(np.concatenate([t[:, [1, 2, 3]], t[:, [0, 2, 3]], t[:, [0, 1, 3]], t[:, [0, 1, 2]]]), axis=1)
    uniq, counts = np.unique(f, axis=0, return_counts=True)
    b = uniq[counts == 1]
    return 0.5 * np.linalg.norm(np.cross(v[b[:, 1]] - v[b[:, 0]], v[b[:, 2]] - v[b[:, 0]]), axis=1).sum()


@pytest.mark.parametrize("args, message", [
    ({"select": "all"}, "operations[0].remesh.edge_length:"),
    ({"edge_length": 0.1}, "operations[0].remesh.select: required"),
    ({"select": {"ball": 1}, "edge_length": 0.1}, "operations[0].remesh.select: unknown selection"),
    ({"select": "all", "edge_length": 0.1, "split": "yes"}, "operations[0].remesh.split:"),
    ({"select": "all", "edge_length": 0.1, "steps": 5}, "operations[0].remesh: steps, views and size"),
])
def test_bad_remesh_entries_are_one_line(args, message):
    v, t = cube_cage()
    fld = Field(random_neural(3, seed=2), v, t)
    with pytest.raises(RadfieldError) as info:
        apply_operations(fld, parse_spec({"operations": [{"remesh": args}]}), EditContext())
    assert str(info.value).startswith(message) and "\n" not in str(info.value)
    assert len(fld.cage_tets) == 6
    with pytest.raises(RadfieldError, match=r"^operations\[0\]\.remesh: this field has no cage"):
        apply_operations(Field(random_neural(3, seed=2)), parse_spec({"operations": [{"remesh": {"select": "all", "edge_length": 1}}]}), EditContext())


def test_remesh_with_split_halves_large_primitives_and_retrains_them_against_the_original():
    prims = random_neural(24, sh_degree=0, extent=0.7, scale=0.18, b2=2.0, seed=5)
    out, note, v, t = remeshed(prims, [0.4, 0.4, 0.4], split=True, steps=40, views=6, size=32)
    assert note["split"] > 0 and note["retrained"] >= 2 and len(out.prims) == len(prims) + note["split"]
    # no primitive is larger than the new tet holding its centre any more, unless 3 rounds did not suffice
    old = {tuple(r) for r in np.sort(t, axis=1).tolist()}
    new_tets = np.flatnonzero([tuple(r) not in old for r in np.sort(out.cage_tets, axis=1).tolist()])
    assert len(oversized(out, new_tets)) < note["split"]
    # the primitives that were not split stay bit-identical (they come first)
    unsplit = len(out.prims) - note["retrained"]
    for i in range(unsplit):
        j = torch.nonzero((prims.means == out.prims.means[i]).all(1)).squeeze(1)
        assert len(j) == 1 and all(torch.equal(getattr(out.prims, n)[i], t[j[0]]) for n, t in prims.tensors().items())
    assert unsplit > 0
    # the split field is close to the original, and retraining does not make it worse
    assert note["psnr_after"] >= note["psnr_split"] and note["psnr_after"] > 25.0
    cam = Camera(fx=40.0, fy=40.0, cx=16, cy=16, width=32, height=32, c2w=look_at((0.5, -3, 0.8), (0, 0, 0)))

    assert float(psnr(render(out.prims, cam).color.clamp(0, 1), render(prims, cam).color.clamp(0, 1))) > 25.0
