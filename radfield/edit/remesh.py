"""Remeshing part of the cage (Neural Impostor §4.2) so later deformations can be finer there.

    - remesh: {select: SELECTION, edge_length: L}
    - remesh: {select: SELECTION, edge_length: L, split: true, steps: 100, views: 12, size: 48}

Conforming longest-edge bisection: while some edge of a tet that meets the selection is longer
than L, the longest such edges (at most one per tet in a round) are split at their
midpoints, and every tet around a split edge (a, b) becomes the two tets with b, resp. a, replaced
by the midpoint m. Splitting all tets around an edge at once keeps the cage one conforming tet mesh
(no hanging vertices, the rest of the cage untouched), each half keeps the orientation and half
the volume, and the union of the tets is unchanged. The primitives are then re-bound to the new
tets. A primitive's density does not live in the cage, so nothing is retrained: the remeshed,
undeformed field is the same model, and the new vertices sit at midpoints, so an undeformed cage
maps every centre to itself.

`split: true` (optional) also splits the primitives larger than the new tets, so that a later
deformation of the fine cage moves their parts separately: a primitive whose centre lies in a new
tet and whose diameter 2·max(s) exceeds that tet's longest edge is halved along its longest axis
(deform.split_primitives, the density-preserving split of the deformation's non-uniform case;
up to 3 rounds). The halves' union is not exactly the parent ellipsoid, so the halves are then
retrained locally with the original field as teacher (retrain.retrain: stage 1 to the parents'
density Σ σ_j/max s_j at points of the halves, stage 2 to renders of the original field from
`views` cameras around them; everything else frozen and bit-identical). The note records `split`
(halvings), `psnr_split` (the split field against the original on those views, before
retraining) and `psnr_after` (after).
"""

from __future__ import annotations

import time

import numpy as np
import torch

from radfield.errors import RadfieldError
from radfield.core import kinds
from radfield.edit.affine import check_cage_orientation
from radfield.edit.field import Field
from radfield.edit.select import number, signed_distance
from radfield.edit.spec import check_keys, operation

_EDGES = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])


def bisect_region(vertices: np.ndarray, tets: np.ndarray, signed_distance, edge_length: float,
                  max_rounds: int = 64, max_tets: int = 2_000_000) -> tuple[np.ndarray, np.ndarray, int]:
    """Refine (module docstring) until no edge of a tet that may meet the region (`signed_distance`:
    points (n, 3) -> (n,), negative inside) is longer than edge_length. Returns vertices, tets, rounds."""
    v, t = np.asarray(vertices, np.float64), np.asarray(tets, np.int64).copy()
    for rounds in range(max_rounds):
        pairs = np.sort(t[:, _EDGES], axis=2).reshape(-1, 2)                   # (6T, 2)
        edges, edge_of = np.unique(pairs, axis=0, return_inverse=True)
        edge_of = edge_of.reshape(len(t), 6)
        length = np.linalg.norm(v[edges[:, 1]] - v[edges[:, 0]], axis=1)
        mid = 0.5 * (v[edges[:, 0]] + v[edges[:, 1]])
        # edges of the tets that may meet the region: the signed distance of the centroid is within
        # the tet's reach (1-Lipschitz, so conservative; the margin shrinks with the tets)
        corners = v[t]
        centroid = corners.mean(1)
        reach = np.linalg.norm(corners - centroid[:, None], axis=2).max(1)
        meets = signed_distance(centroid) <= reach
        cand = np.zeros(len(edges), bool)
        cand[edge_of[meets].reshape(-1)] = True
        cand = np.flatnonzero(cand & (length > edge_length))
        if cand.size == 0:
            return v, t, rounds
        if len(t) > max_tets:
            raise RadfieldError(f"remesh: more than {max_tets} tets; raise edge_length")
        cand = cand[np.argsort(-length[cand], kind="stable")]
        # tets around each edge, grouped
        flat_t = np.repeat(np.arange(len(t)), 6)
        order = np.argsort(edge_of.reshape(-1), kind="stable")
        starts = np.searchsorted(edge_of.reshape(-1)[order], np.arange(len(edges) + 1))
        taken = np.zeros(len(t), bool)
        split_tet, split_edge = [], []
        for e in cand:                       # greedy: longest first, no tet split twice in a round
            around = flat_t[order[starts[e]:starts[e + 1]]]
            if taken[around].any():
                continue
            taken[around] = True
            split_tet.append(around)
            split_edge.append(np.full(len(around), e))
        split_tet, split_edge = np.concatenate(split_tet), np.concatenate(split_edge)
        accepted = np.unique(split_edge)
        new_index = np.full(len(edges), -1)
        new_index[accepted] = len(v) + np.arange(len(accepted))
        v = np.concatenate([v, mid[accepted]])
        a, b = edges[split_edge, 0], edges[split_edge, 1]
        m = new_index[split_edge]
        old = t[split_tet]
        first, second = old.copy(), old.copy()
        first[old == b[:, None]] = m                # (a, m, ...) keeps a
        second[old == a[:, None]] = m               # (m, b, ...) keeps b
        keep = np.ones(len(t), bool)
        keep[split_tet] = False
        t = np.concatenate([t[keep], first, second])
    return v, t, max_rounds


SPLIT_ROUNDS = 3


def oversized(fld: Field, new_tets: np.ndarray) -> np.ndarray:
    """Primitives whose centre lies in one of `new_tets` (indices) and whose diameter 2·max(s)
    exceeds the longest edge of that tet."""
    corners = fld.cage_vertices[fld.cage_tets]                               # (T, 4, 3)
    longest = np.linalg.norm(corners[:, _EDGES[:, 1]] - corners[:, _EDGES[:, 0]], axis=2).max(1)
    is_new = np.zeros(len(fld.cage_tets), bool)
    is_new[new_tets] = True
    diameter = 2 * fld.prims.scales.detach().cpu().double().amax(-1).numpy()
    bound = fld.tet >= 0
    out = np.zeros(len(fld.prims), bool)
    out[bound] = is_new[fld.tet[bound]] & (diameter[bound] > longest[fld.tet[bound]])
    return np.flatnonzero(out)


def split_and_retrain(fld: Field, new_tets: np.ndarray, steps: int, views: int, size: int, seed: int, log):
    """The field with its oversized primitives split (module docstring) and the halves retrained
    against the original field. Returns the field and the figures."""
    from radfield.core.kinds import neural_density
    from radfield.edit import retrain
    from radfield.edit.compose import concat_prims
    from radfield.edit.affine import split_primitives

    original = fld.prims
    # which original primitive each current one descends from (split_primitives puts the kept ones
    # first, then the first halves, then the second halves)
    origin = np.arange(len(original))
    halvings = 0
    for _ in range(SPLIT_ROUNDS):
        flagged = oversized(fld, new_tets)
        if flagged.size == 0:
            break
        halvings += flagged.size
        keep = np.ones(len(fld.prims), bool)
        keep[flagged] = False
        origin = np.concatenate([origin[keep], origin[flagged], origin[flagged]])
        fld = fld.with_prims(split_primitives(fld.prims, flagged))
    figures = {"split": int(halvings)}
    if halvings == 0:
        return fld, figures
    touched = np.bincount(origin, minlength=len(original))[origin] > 1      # descends from a split primitive
    frozen, student = fld.prims.select(torch.as_tensor(np.flatnonzero(~touched))), fld.prims.select(torch.as_tensor(np.flatnonzero(touched)))
    split_parents = original.select(torch.as_tensor(np.unique(origin[touched])))
    # stage 1 target: the parents' density at points of the halves (what the halves replace)
    s64 = student.to(dtype=torch.float64).map(lambda t: t.detach())
    pts = neural_density.ellipsoid_points(s64, neural_density.unit_ball_samples(48, seed + 1)).reshape(-1, 3)
    p64 = split_parents.to(dtype=torch.float64).map(lambda t: t.detach())
    with torch.no_grad():
        target = torch.cat([neural_density.pair_density(p64, pts[lo:lo + 2048]).sum(1) for lo in range(0, len(pts), 2048)])
    cameras = retrain.orbit_around(student, np.arange(len(student)), views, size)
    with torch.no_grad():
        targets = [retrain.render_image(original.to(dtype=torch.float32), cam).double() for cam in cameras]
    log(f"remesh: split {halvings} primitives into {len(student)}; retraining them against the original")
    fitted, fit = retrain.retrain(frozen, student, pts, target, cameras, targets, steps1=steps, steps2=steps, seed=seed, log=log)
    prims = concat_prims(frozen, fitted.to(dtype=frozen.means.dtype))
    out = fld.with_prims(prims)
    figures.update({"retrained": len(student), "psnr_split": round(fit["psnr_before"], 3),
                    "psnr_after": round(fit["psnr_after"], 3), "best_stage": fit["best_stage"],
                    "stage1_seconds": round(fit["stage1_seconds"], 2), "stage2_seconds": round(fit["stage2_seconds"], 2)})
    return out, figures


@operation("remesh")
def remesh(fld: Field, args, ctx) -> Field:
    where = ctx.where
    check_keys(args, {"select", "edge_length", "split", "steps", "views", "size"}, where)
    if not fld.has_cage:
        raise RadfieldError(f"{where}: this field has no cage to remesh")
    check_cage_orientation(fld, where)   # a cage folded by a closed-form edit cannot be bisected and rebound
    if "select" not in args:
        raise RadfieldError(f"{where}.select: required (all, box, sphere or plane)")
    edge_length = number(args, "edge_length", where, positive=True)
    split = args.get("split", False)
    if not isinstance(split, bool):
        raise RadfieldError(f"{where}.split: expected true or false, got {split!r}")
    if not split and any(k in args for k in ("steps", "views", "size")):
        raise RadfieldError(f"{where}: steps, views and size set the retraining of split: true")
    if split and not kinds.of(fld.prims).retrainable_locally:
        raise RadfieldError(f"{where}.split: local retraining needs a neural-primitive model")
    steps = int(number(args, "steps", where, default=100, positive=True))
    views = int(number(args, "views", where, default=12, positive=True))
    size = int(number(args, "size", where, default=48, positive=True))
    selection = args["select"]
    signed_distance(selection, np.zeros((1, 3)), f"{where}.select")       # validate before any work
    t0 = time.perf_counter()
    before = len(fld.cage_tets)
    v, t, rounds = bisect_region(fld.cage_vertices, fld.cage_tets,
                                 lambda p: signed_distance(selection, p, f"{where}.select"), edge_length)
    out = Field(fld.prims, v, t, notes=list(fld.notes))
    out.rebind()
    note = {"operation": "remesh", "tets_before": before, "tets_after": len(t), "vertices_after": len(v),
            "rounds": rounds}
    if split:
        old = {tuple(row) for row in np.sort(fld.cage_tets, axis=1).tolist()}
        new_tets = np.flatnonzero([tuple(row) not in old for row in np.sort(t, axis=1).tolist()])
        out, figures = split_and_retrain(out, new_tets, steps, views, size, ctx.seed, ctx.log)
        note.update(figures)
    note["seconds"] = round(time.perf_counter() - t0, 3)
    out.notes.append(note)
    ctx.log(f"remesh: {before} -> {len(t)} tets in {rounds} rounds"
            + (f", {note['split']} primitives split" if split else ""))
    return out
