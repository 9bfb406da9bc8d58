"""Exact deformation of primitives by affine maps, a cage's or an operation's (Neural Impostor §4.1
on splattable neural primitives).

Moving the cage vertices gives each tet an affine map x ↦ A x + b with A = E' E⁻¹, E and E' the
edge matrices [v1 − v0, v2 − v0, v3 − v0] of the rest and the deformed tet. A primitive bound to a
tet (barycentric λ of its centre) is mapped exactly by its A (docs/usage.md, "How primitives follow the cage (exact)"):
- μ' = Σ λ_i v'_i (= A μ + b of its tet);
- the bounding ellipsoid R S becomes A R S = U Σ Vᵀ (SVD): R' = U (det +1), s' = Σ;
- the density composes with the inverse map: u = (x − μ)/max(s) and x = A⁻¹(x' − b), so
  W1 u = (max(s')/max(s)) W1 A⁻¹ u' and W1' = (max(s')/max(s)) W1 A⁻¹, with b1, W2, b2 unchanged;
- a windowed model's window 1.5 (1 − r²) maps exactly too (the flag is kept): S'⁻¹R'ᵀ(x' − μ') =
  Vᵀ S⁻¹Rᵀ(x − μ), so every point keeps its r²;
- SH coefficients turn with the rotation part of A (polar decomposition A = R_p P), band by band;
- Gaussians: Σ' = A Σ Aᵀ through the same SVD, the same SH rotation, opacity unchanged.
The geometry and SH are mapped here for every kind; what happens to a kind's own tensors (the MLP
above) is its `deformed` and `halved` hooks' (radfield.core.kinds).

Where a primitive goes and which A it uses (`gradient`; docs/usage.md "How primitives follow the cage"):
- "map" (the built-in operations transform, twist, bend, taper: their default): the operation's
  own smooth map φ and its Jacobian J = ∂φ/∂x evaluated at the centre, μ' = φ(μ), A = J(μ)
  (`map_field`; the cage vertices move by φ too). No cage interpolation at all: exact for the
  user's map whatever the cage's resolution, and it does not need the cage's tets to stay
  positive;
- "smooth" (a cage moved by a file, an animation or the simulation: the default): the centre
  from the barycentric blend of the corners' half-step Taylor predictions,
  μ' = Σ λ_i (v'_i + ½ F_i (μ − v_i)), the mean of the linear interpolation Σ λ_i v'_i and of
  the Taylor blend Σ λ_i (v'_i + F_i (μ − v_i)), with F_i the deformation gradient and H_i the
  Hessian at vertex i of a quadratic fitted to its neighbourhood (`fitted_gradients`). Why the
  mean: for a smooth map φ with Hessian H, the linear interpolation errs by
  +½ Σ λ_i (v_i − μ)ᵀH(v_i − μ) and the Taylor blend (exact gradients) by exactly minus that, so
  the mean is third-order accurate. A comes from the same fits, A = Σ λ_i (F_i + ½ H_i (μ − v_i))
  (`smooth_jacobians`: the mean of the linear interpolation of the F_i and of the corners'
  first-order predictions F_i + H_i (μ − v_i), third-order for the same reason), not from the
  tet-mean gradients G_i, only first-order accurate where the map bends; and a primitive is split
  where this field varies across it, not where the tets' maps jump (`nonuniformity`). Exact for
  affine cage maps (every part is);
- "centre": μ' = Σ λ_i v'_i, A = Σ λ_i G_i, the deformation gradient interpolated at the centre
  from vertex gradients G_i (the volume-weighted mean of the A of the tets around vertex i),
  smooth across tet faces;
- "tet": μ' = Σ λ_i v'_i and the affine map of the tet holding the centre: exactly the cage's
  piecewise-linear map at μ (discontinuous across tet faces).
A primitive whose tet and vertex gradients are exactly the identity (and, "smooth", whose corners'
fit neighbourhoods did not move) keeps its parameters bit for bit (so an identity cage, or a local
edit far away, changes nothing: the fits are local, never a global interpolant of the cage).

`preserve_opacity` (Neural Impostor's behaviour: optical depth in rest-space distance): the
renderer's optical depth I of an edited primitive becomes I · max(s')·|A⁻¹d̂|/max(s) = I·√(d̂ᵀ G d̂)
with G = (max(s')/max(s))² A⁻ᵀA⁻¹, stored per primitive as the optional model tensor `rest_metric`
(P, 6: G_xx, G_yy, G_zz, G_xy, G_xz, G_yz); core/render/rasterize.py evaluates the factor at the
direction from the camera to μ once per primitive per view (exact on that central ray).
The default (None, "auto") takes it exactly when some primitive's A is not a similarity: under a
similarity G = I, and without it a non-similarity map changes a primitive's optical depth by
max(s)/(max(s')|A⁻¹d̂|), the whole of the affine squash's 1.1 dB loss against the truth
(docs/studies/edit-truth.md: with it squash, twist and bend land within 0.15 dB of the unedited
run at 128 px). A similarity edit therefore writes no `rest_metric`: its model is the plain one.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from radfield.core import kinds
from radfield.core.geometry.cage import bind_to_cage, tet_volumes
from radfield.core.geometry.rotations import quat_to_rotmat, rotmat_to_quat
from radfield.errors import RadfieldError
from radfield.core.splat.sh import rotate_sh
from radfield.edit.field import Field

CAGE_GRADIENTS = ("smooth", "centre", "tet")   # from the moved cage's vertices alone
GRADIENTS = ("map",) + CAGE_GRADIENTS          # "map": an operation's closed-form map (warp.py)
DEFAULT_GRADIENT = "smooth"   # a cage moved by a file, an animation, the simulation (measured: docs/usage.md)
DEFAULT_MAP_GRADIENT = "map"  # the built-in operations whose map is known in closed form
SPLIT_THRESHOLD = 0.5    # relative variation of A across a primitive above which it is split (nonuniformity)
MAX_SPLIT_ROUNDS = 2     # each round halves the flagged primitives along their longest axis


# --- the cage map ---------------------------------------------------------------------------

def check_deformed_cage(rest: np.ndarray, new: np.ndarray, tets: np.ndarray, where: str = "deform") -> None:
    """One-line error naming the degenerate or inverted tets of a deformed cage (never NaNs later)."""
    new = np.asarray(new, np.float64)
    if new.shape != np.shape(rest):
        raise RadfieldError(f"{where}: the deformed cage has {len(new)} vertices, the field's cage {len(rest)}")
    if not np.isfinite(new).all():
        raise RadfieldError(f"{where}: the deformed cage has non-finite vertex coordinates")
    vol_rest, vol_new = tet_volumes(rest, tets), tet_volumes(new, tets)
    bad = np.flatnonzero(vol_new <= 1e-9 * np.abs(vol_rest))
    if bad.size:
        kind = "inverted" if (vol_new[bad] < 0).any() else "degenerate"
        shown = ", ".join(str(t) for t in bad[:10]) + (f", ... ({bad.size} in all)" if bad.size > 10 else "")
        raise RadfieldError(f"{where}: {kind} tets in the deformed cage (volume <= 0): {shown}")


def tet_maps(rest: np.ndarray, new: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per tet A (T, 3, 3), b (T, 3) with x' = A x + b, and `moved` (T,) bool. A tet whose four
    corners did not move gets exactly A = I, b = 0."""
    c, c2 = rest[tets], new[tets]
    e = np.swapaxes(c[:, 1:] - c[:, :1], 1, 2)      # columns v1 − v0, v2 − v0, v3 − v0
    e2 = np.swapaxes(c2[:, 1:] - c2[:, :1], 1, 2)
    a = e2 @ np.linalg.inv(e)                        # A = E' E⁻¹
    b = c2[:, 0] - np.einsum("tij,tj->ti", a, c[:, 0])
    moved = (c != c2).any(axis=(1, 2))
    a[~moved], b[~moved] = np.eye(3), 0.0
    return a, b, moved


def vertex_gradients(a: np.ndarray, moved: np.ndarray, tets: np.ndarray, rest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Volume-weighted mean (V, 3, 3) of the A of the tets around each vertex, and whether it
    differs from the identity (a vertex whose tets all stayed put gets exactly I)."""
    n = len(rest)
    vol = np.abs(tet_volumes(rest, tets))
    grad = np.zeros((n, 3, 3))
    weight = np.zeros(n)
    for k in range(4):
        np.add.at(grad, tets[:, k], vol[:, None, None] * a)
        np.add.at(weight, tets[:, k], vol)
    grad /= np.maximum(weight, 1e-300)[:, None, None]
    changed = np.zeros(n, bool)
    for k in range(4):
        np.logical_or.at(changed, tets[:, k], moved)
    grad[~changed] = np.eye(3)
    grad[weight == 0] = np.eye(3)
    return grad, changed


def check_cage_orientation(fld: Field, where: str = "deform") -> None:
    """A cage with inverted tets (left so by a closed-form map that folds the cage but not the
    field, e.g. a strong twist) cannot carry a cage-based deformation: its piecewise-linear map
    is not a deformation of the object any more. One line telling how to go on."""
    vol = tet_volumes(fld.cage_vertices, fld.cage_tets)
    bad = np.flatnonzero(vol <= 1e-9 * np.median(np.abs(vol)))   # as check_deformed_cage's bound
    if bad.size:
        raise RadfieldError(f"{where}: the field's cage has {bad.size} inverted or flat tets (an earlier closed-form edit folded it); "
                            f"cage-based edits need a valid cage: give one with --cage FILE, or use the built-in "
                            f"operations with gradient: map")


RING_MIN = 12   # neighbours a vertex needs for the 9-term fit (else its two-ring is used)


def _neighbourhoods(tets: np.ndarray, n: int) -> list[np.ndarray]:
    """Every vertex's one-ring (the vertices sharing a tet with it), or its two-ring where the
    one-ring has fewer than RING_MIN vertices; without the vertex itself."""
    import scipy.sparse as sp
    rows = np.concatenate([tets[:, a] for a in range(4) for b in range(4) if a != b])
    cols = np.concatenate([tets[:, b] for a in range(4) for b in range(4) if a != b])
    adj = sp.csr_matrix((np.ones(len(rows), bool), (rows, cols)), shape=(n, n))
    adj.setdiag(False)
    adj.eliminate_zeros()
    ring2 = ((adj + adj @ adj) > 0).tolil()
    ring2.setdiag(False)
    ring1 = adj.tolil()
    return [np.asarray(r1 if len(r1) >= RING_MIN else r2, np.int64) for r1, r2 in zip(ring1.rows, ring2.rows)]


FIT_DISTANCE_POWER = 2   # each neighbour's equation of the vertex fit is divided by |d|^this (fitted_gradients)


def fitted_gradients(rest: np.ndarray, new: np.ndarray, tets: np.ndarray, fallback: np.ndarray,
                     cache: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex i the deformation gradient F_i (V, 3, 3) and the Hessian H_i (V, 3, 3, 3; H_i[c]
    that of component c) of a weighted least-squares quadratic fit of the displacements over its
    neighbourhood (`_neighbourhoods`: its one-ring where that has enough vertices, so an edit stays
    nearly as local as with the tet-mean gradient): (u_j − u_i) ≈ D_i d + ½ dᵀ H_i d, d = v_j − v_i,
    u = v' − v, F_i = I + D_i. The quadratic terms keep the curvature out of the gradient (a one-sided
    mean of tet maps, as at the cage's boundary, is off by O(h); this is off by O(h²)). Each
    neighbour's equation is divided by |d|² (FIT_DISTANCE_POWER): its cubic remainder O(|d|³) then
    counts as O(|d|), so the near neighbours, whose remainder is smaller, weigh more: no length to
    tune, as well conditioned as the plain fit, and half its error of F (45°/unit twist: mean
    0.0181 -> 0.0096 on the 128 px objects run's cage, 0.055 -> 0.025 on a 4³ box cage of it).
    A fit of an affine map is exact; a vertex whose neighbourhood did not move gets exactly I and
    H = 0; a vertex with too few or too ill-placed neighbours for the 9-term fit keeps `fallback`
    (the tet-mean gradient) and H = 0."""
    n = len(rest)
    key = ("rings", id(tets))
    if cache is not None and key in cache and cache[key][0] is tets:
        rings = cache[key][1]
    else:
        rings = _neighbourhoods(tets, n)
        if cache is not None:
            cache[key] = (tets, rings)
    u = new - rest
    grad = np.array(fallback, np.float64, copy=True)
    hess = np.zeros((n, 3, 3, 3))
    eye = np.eye(3)
    pairs = np.array([[0, 0], [1, 1], [2, 2], [0, 1], [0, 2], [1, 2]])   # the quadratic terms' (a, b)
    for i, js in enumerate(rings):
        du = u[js] - u[i]
        if not du.any():
            grad[i] = eye
            continue
        if len(js) < RING_MIN:
            continue
        d = rest[js] - rest[i]
        scale = np.abs(d).max()
        q = d / scale                                # conditioned: unit-sized offsets
        m = np.concatenate([q, 0.5 * q[:, pairs[:, 0]] * q[:, pairs[:, 1]]], 1)
        w = np.linalg.norm(q, axis=1)[:, None] ** -FIT_DISTANCE_POWER
        sv = np.linalg.svd(w * m, compute_uv=False)
        if sv[-1] < 1e-3 * sv[0]:
            continue
        coef = np.linalg.lstsq(w * m, w * du, rcond=None)[0]
        grad[i] = eye + coef[:3].T / scale
        # ½ Σ_ab c_ab d_a d_b with one term per pair: H_aa = c_aa, H_ab = H_ba = ½ c_ab
        quad = coef[3:].T / scale**2                 # (3 components, 6 pairs)
        half = np.where(pairs[:, 0] == pairs[:, 1], 1.0, 0.5)
        hess[i][:, pairs[:, 0], pairs[:, 1]] = half * quad
        hess[i][:, pairs[:, 1], pairs[:, 0]] = half * quad
    return grad, hess


SMOOTH_CHUNK = 1 << 16   # points per block of smooth_jacobians (bounds its memory at ~100k primitives x 7 probes)


def smooth_jacobians(points: np.ndarray, tet: np.ndarray, bary: np.ndarray, rest: np.ndarray, tets: np.ndarray,
                     grad: np.ndarray, hess: np.ndarray) -> np.ndarray:
    """The smooth mode's Jacobian field (N, 3, 3) at points x (N, 3) bound to (tet, bary) of the rest
    cage: A(x) = Σ λ_i (F_i + ½ H_i (x − v_i)) with the vertex fits (F, H) of `fitted_gradients`
    and the clipped barycentric weights λ (a point outside its tet would extrapolate the
    gradients). Continuous across tet faces (the weights of a face's corners agree there, the
    opposite vertex's is 0). Why ½: the linear interpolation of exact gradients Σ λ_i J(v_i) errs
    by +½ Σ λ_i T[v_i − x, v_i − x] (T the third derivative of the map), the blend of each corner's
    first-order prediction Σ λ_i (J(v_i) + H(v_i)(x − v_i)) by minus that, so their mean is
    third-order accurate, as the centre's (module docstring). Exact for affine cage maps."""
    out = np.empty((len(points), 3, 3))
    for lo in range(0, len(points), SMOOTH_CHUNK):
        sl = slice(lo, lo + SMOOTH_CHUNK)
        lam = np.clip(bary[sl], 0.0, None)
        lam /= np.maximum(lam.sum(1, keepdims=True), 1e-300)
        corners = tets[tet[sl]]                                       # (n, 4)
        offset = points[sl, None, :] - rest[corners]                  # x − v_i
        taylor = grad[corners] + 0.5 * np.einsum("nkcab,nkb->nkca", hess[corners], offset)
        out[sl] = np.einsum("nk,nkij->nij", lam, taylor)
    return out


def primitive_maps(fld: Field, new: np.ndarray, gradient: str = DEFAULT_GRADIENT, cache: dict | None = None,
                   fitted: tuple[np.ndarray, np.ndarray] | None = None):
    """For every primitive: A (P, 3, 3), its new centre μ' (P, 3) and whether it changes (P,).
    `fitted`: the vertex fits (F, H) of `fitted_gradients` for this cage pose, when already made
    ("smooth")."""
    if gradient not in CAGE_GRADIENTS:
        raise RadfieldError(f"deform: gradient must be one of {', '.join(CAGE_GRADIENTS)} for a moved cage "
                            f"(map: the built-in operations only), got {gradient!r}")
    rest, tets = fld.cage_vertices, fld.cage_tets
    a_tet, _, moved = tet_maps(rest, new, tets)
    corners = tets[fld.tet]                                   # (P, 4)
    means = np.einsum("pk,pkd->pd", fld.bary, new[corners])   # μ' = Σ λ_i v'_i
    if gradient == "tet":
        return a_tet[fld.tet], means, moved[fld.tet]
    grad, changed = vertex_gradients(a_tet, moved, tets, rest)
    changed_p = changed[corners].any(1) | moved[fld.tet]
    if gradient == "centre":
        # a centre outside its tet (negative λ) would extrapolate the gradients: use the clipped weights
        lam = np.clip(fld.bary, 0.0, None)
        lam /= np.maximum(lam.sum(1, keepdims=True), 1e-300)
        return np.einsum("pk,pkij->pij", lam, grad[corners]), means, changed_p
    # "smooth": the mean of the linear interpolation and of the corners' Taylor predictions (module
    # docstring): their second-order errors cancel. Exact for an affine map x ↦ Fx + b because
    # Σ λ_i v_i = μ (the binding's own λ, extrapolating outside the cage as "tet" does). A from the
    # same fits (smooth_jacobians), not from the tet-mean gradients (O(h) off where the map bends).
    fit, hess = fitted if fitted is not None else fitted_gradients(rest, new, tets, grad, cache)
    moved_v = (fit != np.eye(3)).any(axis=(1, 2)) | hess.any(axis=(1, 2, 3)) | (new != rest).any(1)
    changed_p = changed_p | moved_v[corners].any(1)
    mu = fld.prims.means.detach().double().numpy()
    pred = new[corners] + 0.5 * np.einsum("pkij,pkj->pki", fit[corners], mu[:, None, :] - rest[corners])
    means = np.where(changed_p[:, None], np.einsum("pk,pkd->pd", fld.bary, pred), means)
    a = smooth_jacobians(mu, fld.tet, fld.bary, rest, tets, fit, hess)
    return a, means, changed_p


# --- mapping primitives by per-primitive affine maps ----------------------------------------

def polar_rotation(a: np.ndarray) -> np.ndarray:
    """Rotation part R_p of A = R_p P (P symmetric positive definite), for det A > 0."""
    u, _, vt = np.linalg.svd(a)
    return u @ vt


def is_similarity(a: np.ndarray, tol: float = 1e-9) -> bool:
    """Whether every map of A (S, 3, 3) is a similarity s R (AᵀA = s² I, relative tolerance)."""
    ata = np.einsum("sji,sjk->sik", a, a)
    s2 = np.trace(ata, axis1=1, axis2=2) / 3
    return bool(np.all(np.abs(ata - s2[:, None, None] * np.eye(3)) <= tol * np.maximum(s2, 1e-300)[:, None, None]))


def map_primitives(prims, a: np.ndarray, means: np.ndarray, changed: np.ndarray | None = None,
                   preserve_opacity: bool | None = None):
    """Primitives mapped by per-primitive affine maps A (P, 3, 3) to new centres (P, 3) (module
    docstring). Rows with changed == False keep their parameters exactly. preserve_opacity None:
    where some changed A is not a similarity (module docstring)."""
    p = len(prims)
    a = np.broadcast_to(np.asarray(a, np.float64), (p, 3, 3))
    changed = np.ones(p, bool) if changed is None else np.asarray(changed, bool)
    idx = torch.from_numpy(np.flatnonzero(changed))
    if idx.numel() == 0:
        return prims
    if preserve_opacity is None:
        preserve_opacity = not is_similarity(a[changed])
    sub = prims.select(idx).to(dtype=torch.float64)
    a_t = torch.from_numpy(np.ascontiguousarray(a[changed]))
    rot = quat_to_rotmat(sub.quats)
    scales = torch.exp(sub.log_scales)
    u, sigma, _ = torch.linalg.svd(a_t @ rot * scales[:, None, :])   # A R S = U Σ Vᵀ
    flip = torch.linalg.det(u) < 0
    u[flip, :, 2] = -u[flip, :, 2]                                     # same ellipsoid, a proper rotation
    new = {
        "means": torch.from_numpy(np.ascontiguousarray(means[changed])),
        "log_scales": torch.log(sigma),
        "quats": rotmat_to_quat(u),
        "sh": rotate_sh(sub.sh, torch.from_numpy(polar_rotation(a[changed]))),
    }
    # the kind's own tensors (neural: W1' = (max s'/max s) W1 A⁻¹, and the rest metric)
    out, own = kinds.of(prims).deformed(prims, idx, sub, a_t, scales, sigma, preserve_opacity)
    new.update(own)
    tensors = {}
    for name, value in new.items():
        full = getattr(out, name).clone()
        full[idx] = value.to(full.dtype)
        tensors[name] = full
    return replace(out, **tensors)


def affine_field(fld: Field, a: np.ndarray, t: np.ndarray, preserve_opacity: bool | None = None) -> Field:
    """The whole field (primitives and cage) mapped by one affine map x' = A x + t, exactly."""
    a, t = np.asarray(a, np.float64), np.asarray(t, np.float64)
    if not np.linalg.det(a) > 0:
        raise RadfieldError("transform: the map must keep orientation (det > 0, scale > 0)")
    means = fld.prims.means.detach().double().numpy() @ a.T + t
    prims = map_primitives(fld.prims, a, means, preserve_opacity=preserve_opacity)
    verts = None if fld.cage_vertices is None else fld.cage_vertices @ a.T + t
    return replace(fld, prims=prims, cage_vertices=verts, notes=list(fld.notes))


# --- splitting primitives that straddle a non-uniform deformation ----------------------------

def _probe_points(prims) -> np.ndarray:
    """(P, 7, 3): the centre and the six ends of the ellipsoid's axes at 3/4 of its radii."""
    rot = quat_to_rotmat(prims.quats.detach().double())
    axes = (rot * torch.exp(prims.log_scales.detach().double())[:, None, :]).transpose(1, 2).numpy()  # rows R_i s_i
    mu = prims.means.detach().double().numpy()
    offsets = np.concatenate([np.zeros_like(axes[:, :1]), 0.75 * axes, -0.75 * axes], 1)
    return mu[:, None, :] + offsets


def nonuniformity(fld: Field, a_tet: np.ndarray, cache: dict | None = None,
                  fitted: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Per primitive: max over its probe points of |A_j − A_c|₂ / |A_c|₂ (0 for a uniform
    neighbourhood). A at a point: the map of the tet holding it, A_c that of its centre's tet ("tet",
    "centre"); with `fitted` (the vertex fits (F, H) of `fitted_gradients`) the smooth mode's own
    field `smooth_jacobians` at the probe points, A_c at the centre. The tets' piecewise-constant
    maps jump at every tet face by O(h) even where the map barely bends, so measured on them many
    primitives of a coarse cage straddle a "bend" that is not there (the 128 px objects run on a
    4³ box cage twisted 45°/unit: 353 of 1413 primitives split, 1.5 dB of alpha PSNR lost to the
    halves' approximation, docs/studies/edit-truth.md); the smooth field varies as the map does,
    as the Jacobians of `map_field`'s criterion (none split there either). `cache` (a dict kept by the
    caller) remembers the probes' binding of a field deformed again and again (animation frames)."""
    key = (id(fld.prims), id(fld.cage_vertices))
    if cache is not None and key in cache:
        probes, tets, bary = cache[key][1:]
    else:
        probes = _probe_points(fld.prims).reshape(-1, 3)
        tets, bary = bind_to_cage(probes, (fld.cage_vertices, fld.cage_tets))
        if cache is not None:
            cache[key] = (fld.prims, probes, tets, bary)   # holds the objects, so their ids stay theirs
    p = len(fld.prims)
    if fitted is None:
        a_probe = a_tet[tets].reshape(p, 7, 3, 3)
        a_c = a_tet[fld.tet][:, None]
    else:
        a_probe = smooth_jacobians(probes, tets, bary, fld.cage_vertices, fld.cage_tets, *fitted).reshape(p, 7, 3, 3)
        a_c = a_probe[:, :1]
    diff = np.linalg.norm(a_probe - a_c, ord=2, axis=(-2, -1)).max(1)
    return diff / np.linalg.norm(a_c[:, 0], ord=2, axis=(-2, -1))


def split_primitives(prims, index: np.ndarray):
    """Each primitive of `index` replaced by two halves along its longest axis e (radius a):
    centres μ ± (a/2) e, radius a/2 along e. The density is the same function of x in each half:
    u = (x − μ)/max(s) gives W1_c = (max(s_c)/max(s)) W1, b1_c = b1 + W1 (μ_c − μ)/max(s), and the
    per-size optical depth (1/max(s)) ∫σ keeps its value with W2, b2 scaled by max(s_c)/max(s).
    The halves' union is not exactly the parent ellipsoid (thinner at the cut, wider at the
    quarter points): a split is a small approximation, made only where the cage bends. Halves of a
    windowed model stay windowed, each window falling to 0 on its own ellipsoid (not the parent's):
    part of the same approximation. (The MLP's part is the kind's `halved` hook.)"""
    index = torch.as_tensor(index, dtype=torch.long)
    keep = torch.ones(len(prims), dtype=torch.bool)
    keep[index] = False
    par = prims.select(index)
    rot = quat_to_rotmat(par.quats)
    scales = torch.exp(par.log_scales)
    axis = scales.argmax(-1)
    e = rot.gather(2, axis[:, None, None].expand(-1, 3, 1))[..., 0]          # (S, 3) longest axis
    radius = scales.gather(1, axis[:, None])[:, 0]
    child_scales = scales.clone()
    child_scales.scatter_(1, axis[:, None], (radius / 2)[:, None])
    smax, smax_c = scales.amax(-1), child_scales.amax(-1)
    kind = kinds.of(prims)
    children = []
    for sign in (1.0, -1.0):
        offset = sign * (radius / 2)[:, None] * e
        fields = {"means": par.means + offset, "log_scales": torch.log(child_scales), "quats": par.quats, "sh": par.sh}
        fields.update(kind.halved(par, offset, smax_c / smax))
        children.append(replace(par, **fields))
    parts = [prims.select(keep)] + children
    return replace(prims, **{name: torch.cat([getattr(q, name) for q in parts]) for name in prims.tensors()})


# --- the deformation of a field ---------------------------------------------------------------

def deform_field(fld: Field, new_vertices: np.ndarray, *, gradient: str = DEFAULT_GRADIENT,
                 split: float | None = SPLIT_THRESHOLD, preserve_opacity: bool | None = None,
                 where: str = "deform", cache: dict | None = None, rebind: bool = True) -> Field:
    """The field with its cage moved to `new_vertices` (same topology), every primitive mapped
    exactly (module docstring). `split`: threshold of `nonuniformity` above which a primitive is
    halved first (None: never); `cache`: see `nonuniformity` (and the cage's neighbourhoods);
    `rebind`: bind the primitives to the new cage where μ' left its barycentric place ("smooth";
    animation frames, deformed from the rest field each time, skip it). Appends {"op", "split", "moved_primitives", ...} to the notes."""
    if not fld.has_cage:
        raise RadfieldError(f"{where}: this field has no cage (its run has no tetra stage output)")
    new = np.asarray(new_vertices, np.float64)
    check_cage_orientation(fld, where)
    check_deformed_cage(fld.cage_vertices, new, fld.cage_tets, where)
    a_tet, _, moved = tet_maps(fld.cage_vertices, new, fld.cage_tets)
    fitted = None
    if gradient == "smooth" and moved.any():   # the vertex fits, for the split criterion and the map
        grad, _ = vertex_gradients(a_tet, moved, fld.cage_tets, fld.cage_vertices)
        fitted = fitted_gradients(fld.cage_vertices, new, fld.cage_tets, grad, cache)
    n_split = 0
    if split is not None and moved.any():
        for _ in range(MAX_SPLIT_ROUNDS):
            flagged = np.flatnonzero(nonuniformity(fld, a_tet, cache, fitted) > split)
            if flagged.size == 0:
                break
            n_split += flagged.size
            fld = fld.with_prims(split_primitives(fld.prims, flagged))
    a, means, changed = primitive_maps(fld, new, gradient, cache, fitted)
    prims = map_primitives(fld.prims, a, means, changed, preserve_opacity)
    out = replace(fld, prims=prims, cage_vertices=new, notes=list(fld.notes))
    if gradient == "smooth" and rebind:
        out.rebind()   # μ' is not Σ λ_i v'_i there: bind again for later cage-based edits
    out.notes.append({"operation": where.rsplit(".", 1)[-1], "entry": where, "gradient": gradient,
                      "split": int(n_split), "primitives": len(prims),
                      "moved_primitives": int(changed.sum()), "moved_tets": int(moved.sum())})
    return out


# --- a closed-form map (the built-in operations) ----------------------------------------------

def map_field(fld: Field, phi, jacobian, *, split: float | None = SPLIT_THRESHOLD, preserve_opacity: bool | None = None,
              where: str = "deform", rebind: bool = True) -> tuple[Field, int]:
    """The field mapped by a smooth map known in closed form: `phi` (N, 3) -> (N, 3) and its
    Jacobian `jacobian` (N, 3) -> (N, 3, 3). Every primitive gets μ' = φ(μ), A = J(μ) (then the
    exact per-primitive mapping above); the cage's vertices move by φ, so the edited field's cage
    follows the map for later edits and animation. `split`: a primitive whose Jacobian varies
    over its probe points by more than this (relative, as `nonuniformity`) is halved first.
    Returns the field and the number of cage tets the map inverted (the caller says so: the field
    is fine, its cage is not any more, and cage-based edits of it are refused until re-caged)."""
    n_split = 0
    if split is not None:
        for _ in range(MAX_SPLIT_ROUNDS):
            probes = _probe_points(fld.prims)
            p = len(fld.prims)
            jac = jacobian(probes.reshape(-1, 3)).reshape(p, 7, 3, 3)
            norm_c = np.linalg.norm(jac[:, 0], ord=2, axis=(-2, -1))
            diff = np.linalg.norm(jac - jac[:, :1], ord=2, axis=(-2, -1)).max(1)
            flagged = np.flatnonzero(diff > split * norm_c)
            if flagged.size == 0:
                break
            n_split += flagged.size
            fld = replace(fld, prims=split_primitives(fld.prims, flagged), notes=list(fld.notes))
    mu = fld.prims.means.detach().double().numpy()
    means, a = np.asarray(phi(mu), np.float64), np.asarray(jacobian(mu), np.float64)
    if not (np.isfinite(means).all() and np.isfinite(a).all()):
        raise RadfieldError(f"{where}: the map gives non-finite positions")
    det = np.linalg.det(a)
    folded = np.flatnonzero(det <= 0)
    if folded.size:
        raise RadfieldError(f"{where}: the map folds space at {folded.size} primitives (Jacobian determinant <= 0, "
                            f"e.g. primitive {folded[0]}); use a gentler map or a wider falloff")
    changed = (means != mu).any(1) | (a != np.eye(3)).any(axis=(1, 2))
    prims = map_primitives(fld.prims, a, means, changed, preserve_opacity)
    out = replace(fld, prims=prims, notes=list(fld.notes))
    inverted = 0
    if fld.has_cage:
        new = np.asarray(phi(fld.cage_vertices), np.float64)
        if not np.isfinite(new).all():
            raise RadfieldError(f"{where}: the map gives non-finite cage vertices")
        vol_rest, vol_new = tet_volumes(fld.cage_vertices, fld.cage_tets), tet_volumes(new, fld.cage_tets)
        inverted = int((vol_new <= 1e-9 * np.abs(vol_rest)).sum())
        out.cage_vertices = new
    if inverted:
        # the folded cage carries the field no more (cage-based edits are refused): unbound
        out.tet, out.bary = np.full(len(prims), -1, np.int64), np.zeros((len(prims), 4))
    elif rebind or len(prims) != len(out.tet):
        out.rebind()   # μ' is φ(μ), not Σ λ_i v'_i: bind again for later cage-based edits
    out.notes.append({"operation": where.rsplit(".", 1)[-1], "entry": where, "gradient": "map",
                      "split": int(n_split), "primitives": len(prims), "moved_primitives": int(changed.sum()),
                      "inverted_cage_tets": inverted})
    return out, inverted
