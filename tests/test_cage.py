"""The tetrahedral cage (radfield.core.geometry.cage, fTetWild): coarse, positive, exact point location, volume-weighted samples."""

import meshio
import numpy as np
import pytest

from radfield.errors import RadfieldError
from radfield.core.geometry.cage import build_cage, locate_points, read_cage, sample_in_cage, tet_volumes, write_cage


# torus_envelope, cfg: tests/conftest.py (shared with tests/test_envelope.py)


@pytest.fixture(scope="module")
def torus_cage(torus_envelope, cfg):
    _, v, f, _ = torus_envelope
    return build_cage(v, f, cfg("tetra"))


def test_cage_is_coarse_positive_and_round_trips(torus_envelope, torus_cage, tmp_path):
    surface = torus_envelope[0]
    cv, tets, figures = torus_cage
    assert 100 <= figures["tets"] <= 5000 and figures["tets"] == len(tets)
    assert figures["vertices"] == len(cv) and np.unique(tets).size == len(cv)
    assert (tet_volumes(cv, tets) > 0).all()
    index, _ = locate_points(cv, tets, surface)
    assert (index >= 0).all()  # every surface sample is inside the cage

    write_cage(tmp_path, cv, tets)
    for name in ("cage.vtk", "cage.npz"):
        rv, rt = read_cage(tmp_path / name)
        assert np.array_equal(rt, tets) and np.array_equal(rv, cv)
    assert meshio.read(tmp_path / "cage.vtk").cells_dict["tetra"].shape == tets.shape

    # a user moves vertices in another tool and saves: same topology, new positions
    moved = cv + np.array([0.0, 0.0, 0.1]) * cv[:, :1]
    meshio.write(tmp_path / "edited.vtu", meshio.Mesh(moved, [("tetra", tets)]))
    rv, rt = read_cage(tmp_path / "edited.vtu")
    assert np.array_equal(rt, tets) and np.allclose(rv, moved)


def test_read_cage_errors(tmp_path):
    (tmp_path / "junk.vtk").write_text("garbage")
    with pytest.raises(RadfieldError, match="junk.vtk"):
        read_cage(tmp_path / "junk.vtk")
    np.savez(tmp_path / "bad.npz", vertices=np.zeros((3, 3)), tets=np.array([[0, 1, 2, 3]]))
    with pytest.raises(RadfieldError, match="indices"):
        read_cage(tmp_path / "bad.npz")


def test_locate_points_is_exact(torus_cage):
    cv, tets, _ = torus_cage
    rng = np.random.default_rng(4)
    lo, hi = cv.min(0), cv.max(0)
    points = rng.uniform(lo - 0.1, hi + 0.1, (20000, 3))
    index, bary = locate_points(cv, tets, points, k=4)
    inside = index >= 0
    assert 0.1 < inside.mean() < 0.9
    assert np.allclose(np.einsum("nk,nkd->nd", bary[inside], cv[tets[index[inside]]]), points[inside])
    assert np.allclose(bary[inside].sum(1), 1) and (bary[inside] >= -1e-9).all()
    # brute force on a subset: a point is inside iff some tet has all barycentrics >= 0
    corners = cv[tets]
    T = np.linalg.inv(np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1)))
    for p, i in zip(points[:400], index[:400]):
        b = np.einsum("tij,tj->ti", T, p - corners[:, 0])
        holds = (b >= -1e-9).all(1) & (b.sum(1) <= 1 + 1e-9)
        assert holds.any() == (i >= 0)
        if i >= 0:
            assert holds[i]


def test_sample_in_cage_is_volume_weighted(torus_cage):
    cv, tets, figures = torus_cage
    points, index, bary = sample_in_cage(cv, tets, 40000, rng=5)
    assert np.allclose(np.einsum("nk,nkd->nd", bary, cv[tets[index]]), points)
    located, _ = locate_points(cv, tets, points)
    assert (located >= 0).all()
    volumes = tet_volumes(cv, tets)
    centroid = (volumes[:, None] * cv[tets].mean(1)).sum(0) / volumes.sum()
    spread = points.std(0) / np.sqrt(len(points))
    assert np.all(np.abs(points.mean(0) - centroid) < 5 * spread)
    # the largest tets get proportionally more samples
    big = volumes > np.median(volumes)
    assert np.isin(index, np.flatnonzero(big)).mean() == pytest.approx(volumes[big].sum() / volumes.sum(), abs=0.01)
