"""The tetrahedral cage: a coarse tet mesh of the envelope (pytetwild / fTetWild; `fallback_cage`
when fTetWild fails), its files, and the point queries that the init and train stages and the
editor share (which tet holds a point, uniform samples inside, the binding of primitives to tets).

A cage is `vertices` (V, 3) float64 and `tets` (T, 4) int64, stored with positive orientation:
det[v1 - v0, v2 - v0, v3 - v0] > 0. Files: `cage.vtk` (legacy VTK through meshio: ParaView,
Houdini, Blender add-ons) and `cage.npz` (`vertices`, `tets`); `read_cage` also reads a cage whose
vertices were moved in another tool (.vtk/.vtu/.msh/.npz).

A binding (`binding.npz`) records for every primitive `tet` (P,) int64, the cage tet of its
centre, and `bary` (P, 4) float64, the centre's barycentric coordinates in that tet (weights of its
4 corners, summing to 1): moving the cage vertices moves the centre to the same weights of the
moved corners. `tet` is -1 everywhere when the run has no cage.
"""

from __future__ import annotations

import contextlib
import io
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
# pytetwild and meshio are imported in the functions that use them: editing, rendering and a run
# without a cage need neither (a cage.npz is read with numpy)

from radfield.util.atomic import atomic_write
from radfield.errors import RadfieldError
from radfield import run as layout

CAGE_VTK = "cage.vtk"
CAGE_NPZ = layout.CAGE_FILE
CAGE_FILES = (CAGE_VTK, CAGE_NPZ)


def build_cage(vertices: np.ndarray, faces: np.ndarray, cfg: dict):
    """Tetrahedralise a closed envelope (vertices (V, 3), faces (F, 3)) with the `tetra` section
    `cfg` of the config. Returns cage vertices (V', 3) float64, tets (T, 4) int64 with positive
    volumes, and the figures `tets`, `vertices`, `volume`. fTetWild is not bit-deterministic:
    counts vary by a few percent between runs. With the defaults an envelope of ~1000 faces gives
    ~1000-2000 tets; raise `edge_length_fac` / `epsilon` for fewer."""
    import pytetwild

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int32)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) < 4:
        raise RadfieldError(f"cage: need a closed triangle mesh, got vertices {v.shape} and faces {f.shape}")
    # fTetWild writes a debug file (_tracked_surface.stl) into the working directory: keep it out of the user's
    with tempfile.TemporaryDirectory() as scratch, contextlib.chdir(scratch):
        cage_v, tets = pytetwild.tetrahedralize(
            v, f, edge_length_fac=cfg["edge_length_fac"], epsilon=cfg["epsilon"], coarsen=cfg["coarsen"],
            optimize=cfg["optimize"], num_threads=cfg["num_threads"], quiet=True,
        )
    if len(tets) == 0:
        raise RadfieldError("cage: fTetWild produced no tets (is the envelope closed?)")
    cage_v, tets = _compact(np.asarray(cage_v, np.float64), np.asarray(tets, np.int64))
    volumes = tet_volumes(cage_v, tets)
    flip = volumes < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]  # swapping two corners flips the orientation
    volumes = np.abs(volumes)
    if not (volumes > 0).all():
        raise RadfieldError(f"cage: {(volumes <= 0).sum()} degenerate tets")
    return cage_v, tets, {"tets": len(tets), "vertices": len(cage_v), "volume": float(volumes.sum())}


def _compact(v: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop vertices no tet uses, renumbering the tets."""
    used, inverse = np.unique(tets, return_inverse=True)
    return v[used], inverse.reshape(tets.shape)


def tet_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes (T,) = det[v1 - v0, v2 - v0, v3 - v0] / 6."""
    c = np.asarray(vertices, np.float64)[tets]
    return np.linalg.det(c[:, 1:] - c[:, :1]) / 6.0


def write_cage(out_dir, vertices: np.ndarray, tets: np.ndarray) -> list[Path]:
    """Write `cage.vtk` (legacy VTK unstructured grid, through meshio: opens in ParaView, Houdini,
    Blender add-ons) and `cage.npz` (`vertices` (V, 3) float64, `tets` (T, 4) int64), atomically."""
    import meshio

    out_dir = Path(out_dir)
    mesh = meshio.Mesh(np.asarray(vertices, np.float64), [("tetra", np.asarray(tets, np.int64))])
    atomic_write(out_dir / CAGE_VTK, lambda tmp: meshio.write(tmp, mesh, file_format="vtk"))
    atomic_write(out_dir / CAGE_NPZ, lambda tmp: np.savez(tmp, vertices=mesh.points, tets=mesh.cells[0].data))
    return [out_dir / name for name in CAGE_FILES]


def read_cage(path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 and tets (T, 4) int64 from `cage.npz` or any tet-mesh file meshio
    reads (.vtk, .vtu, .msh, ...), e.g. a cage whose vertices were moved in another tool."""
    path = Path(path)
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                v, t = data["vertices"], data["tets"]
        else:
            import meshio

            # meshio prints its complaints and calls sys.exit on an unreadable file
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                mesh = meshio.read(path)
            blocks = [c.data for c in mesh.cells if c.type == "tetra"]
            if not blocks:
                raise RadfieldError(f"{path}: no tetrahedra in this mesh")
            v, t = mesh.points, np.concatenate(blocks)
    except RadfieldError:
        raise
    except (Exception, SystemExit) as exc:  # meshio and numpy raise many types for bad files
        raise RadfieldError(f"{path}: not a readable cage ({type(exc).__name__}: {exc})") from None
    v, t = np.asarray(v, np.float64), np.asarray(t, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or not np.isfinite(v).all():
        raise RadfieldError(f"{path}: cage vertices must be finite (V, 3), got {v.shape}")
    if t.ndim != 2 or t.shape[1] != 4 or len(t) == 0 or t.min() < 0 or t.max() >= len(v):
        raise RadfieldError(f"{path}: cage tets must be (T, 4) indices into the {len(v)} vertices")
    return v, t


def locate_points(cage_vertices: np.ndarray, tets: np.ndarray, points: np.ndarray, k: int = 8,
                  chunk: int = 65536, eps: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """For points (N, 3): the tet holding each one (N,) int64, -1 outside the cage, and its
    barycentric coordinates (N, 4) (weights of the tet's corners, summing to 1; zeros outside).

    Exact for any tet mesh: candidates are the tets with the nearest centroids (cKDTree); a point
    not inside any of its k candidates is re-queried with 2k, ... until the k-th centroid is farther
    than any tet reaches from its centroid. On a shared face the tet holding it most deeply wins."""
    v = np.asarray(cage_vertices, np.float64)
    t = np.asarray(tets, np.int64)
    p = np.asarray(points, np.float64).reshape(-1, 3)
    corners = v[t]
    centroids = corners.mean(1)
    reach = np.linalg.norm(corners - centroids[:, None], axis=2).max()  # no tet extends farther
    edges = np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1))  # columns v1-v0, v2-v0, v3-v0
    with np.errstate(all="ignore"):
        singular = np.abs(np.linalg.det(edges)) < 1e-300
        edges[singular] = np.eye(3)
        inverse = np.linalg.inv(edges)
    inverse[singular] = np.nan  # a flat tet holds nothing
    tree = cKDTree(centroids)

    index = np.full(len(p), -1, np.int64)
    bary = np.zeros((len(p), 4))
    for start in range(0, len(p), chunk):
        todo = np.arange(start, min(start + chunk, len(p)))
        kk = min(k, len(t))
        while todo.size:
            dist, cand = tree.query(p[todo], k=kk)
            dist, cand = dist.reshape(len(todo), kk), cand.reshape(len(todo), kk)
            b123 = np.einsum("nkij,nkj->nki", inverse[cand], p[todo, None] - corners[cand, 0])
            b = np.concatenate([1.0 - b123.sum(-1, keepdims=True), b123], -1)
            depth = np.nan_to_num(b.min(-1), nan=-np.inf)
            best = depth.argmax(1)
            rows = np.arange(len(todo))
            found = depth[rows, best] >= -eps
            index[todo[found]] = cand[rows, best][found]
            bary[todo[found]] = b[rows, best][found]
            # only points whose k-th candidate is still within reach may lie in a farther tet
            todo = todo[~found & (dist[:, -1] <= reach)]
            if kk == len(t):
                break
            kk = min(2 * kk, len(t))
    return index, bary


def sample_in_cage(cage_vertices: np.ndarray, tets: np.ndarray, n: int, rng=None):
    """`n` points uniform in the cage's volume: a tet drawn with probability proportional to its
    volume, then a uniform point in it (flat Dirichlet barycentrics). Returns points (n, 3),
    tet index (n,) and barycentrics (n, 4). `rng`: numpy Generator or seed."""
    rng = np.random.default_rng(rng)
    v = np.asarray(cage_vertices, np.float64)
    t = np.asarray(tets, np.int64)
    volumes = np.abs(tet_volumes(v, t))
    index = rng.choice(len(t), size=n, p=volumes / volumes.sum())
    bary = rng.dirichlet(np.ones(4), size=n)
    points = np.einsum("nk,nkd->nd", bary, v[t[index]])
    return points, index, bary


def bind_to_cage(means: np.ndarray, cage) -> tuple[np.ndarray, np.ndarray]:
    """Binding of points (P, 3) (primitive centres) to `cage`, a cage file or a (vertices, tets)
    pair: tet (P,) int64 and
    barycentric coordinates (P, 4). A point outside the cage (training moves primitives) gets the
    tet it is least outside of among those with the nearest centroids, with barycentric
    coordinates that extrapolate that tet's affine map (some negative), so it still follows edits."""
    v, t = cage if isinstance(cage, tuple) else read_cage(cage)
    v, t = np.asarray(v, np.float64), np.asarray(t, np.int64)
    p = np.asarray(means, np.float64).reshape(-1, 3)
    tet, bary = locate_points(v, t, p)
    outside = np.flatnonzero(tet < 0)
    if outside.size:
        corners = v[t]
        _, cand = cKDTree(corners.mean(1)).query(p[outside], k=min(8, len(t)))
        cand = cand.reshape(len(outside), -1)
        edges = np.swapaxes(corners[cand, 1:] - corners[cand, :1], -1, -2)  # columns v1-v0, v2-v0, v3-v0
        b123 = np.linalg.solve(edges, (p[outside, None] - corners[cand, 0])[..., None])[..., 0]
        b = np.concatenate([1.0 - b123.sum(-1, keepdims=True), b123], -1)
        best = b.min(-1).argmax(1)
        rows = np.arange(len(outside))
        tet[outside], bary[outside] = cand[rows, best], b[rows, best]
    return tet, bary


def write_binding(path, means: np.ndarray, cage_npz) -> None:
    """Write `binding.npz` (module docstring) of primitive centres (P, 3) to the cage in
    `cage_npz`, or an unbound one (tet -1) when `cage_npz` is None (the run has no cage)."""
    if cage_npz is None:
        tet, bary = np.full(len(means), -1, np.int64), np.zeros((len(means), 4))
    else:
        tet, bary = bind_to_cage(means, cage_npz)
    atomic_write(Path(path), lambda tmp: np.savez(tmp, tet=tet, bary=bary))


def fallback_cage(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """A cage that cannot fail, for when fTetWild does: the Delaunay tets of the envelope's
    vertices whose centroids lie inside it (all of them, the convex hull, when none does), or 6
    tets of the vertices' bounding box when they are degenerate (on a plane). Returns vertices,
    positively oriented tets and the name of what was built ("delaunay" or "box")."""
    from scipy.spatial import Delaunay, QhullError

    from radfield.core.geometry.envelope import inside_envelope  # here: only the fallback needs VTK

    v = np.asarray(vertices, np.float64)
    try:
        tets = Delaunay(v).simplices.astype(np.int64)
        tets = tets[np.abs(tet_volumes(v, tets)) > 1e-12 * max(float(np.ptp(v, 0).max()), 1e-300) ** 3]
        if len(tets) == 0:
            raise QhullError("only flat tets")
        inside = inside_envelope(v[tets].mean(1), v, faces)
        tets, name = (tets[inside] if inside.any() else tets), "delaunay"
    except (QhullError, ValueError):
        lo, hi = v.min(0), v.max(0)
        grow = 1e-3 * max(float((hi - lo).max()), 1.0)
        lo, hi = lo - grow, hi + grow
        v = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        tets, name = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]]), "box"
    v, tets = _compact(v, tets)
    flip = tet_volumes(v, tets) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return v, tets, name
