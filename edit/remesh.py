"""Remeshing part of the cage (Neural Impostor §4.2) so later deformations can be finer there.

    - remesh: {select: SELECTION, edge_length: L}

Conforming longest-edge bisection: while some edge of a tet that meets the selection is longer
than L, the longest such edges (at most one per tet in a round) are split at their
midpoints, and every tet around a split edge (a, b) becomes the two tets with b, resp. a, replaced
by the midpoint m. Splitting all tets around an edge at once keeps the cage one conforming tet mesh
(no hanging vertices, the rest of the cage untouched), each half keeps the orientation and half
the volume, and the union of the tets is unchanged. The primitives are then re-bound to the new
tets. A primitive's density does not live in the cage, so nothing is retrained: the remeshed,
undeformed field is the same model, and the new vertices sit at midpoints, so an undeformed cage
maps every centre to itself.
"""

from __future__ import annotations

import time

import numpy as np

from radfield.core.errors import RadfieldError
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


@operation("remesh")
def remesh(fld: Field, args, ctx) -> Field:
    where = ctx.where
    if "split" in args:
        raise RadfieldError(f"{where}.split: splitting primitives is not implemented")
    check_keys(args, {"select", "edge_length"}, where)
    if not fld.has_cage:
        raise RadfieldError(f"{where}: this field has no cage to remesh")
    if "select" not in args:
        raise RadfieldError(f"{where}.select: required (all, box, sphere or plane)")
    edge_length = number(args, "edge_length", where, positive=True)
    selection = args["select"]
    signed_distance(selection, np.zeros((1, 3)), f"{where}.select")       # validate before any work
    t0 = time.perf_counter()
    before = len(fld.cage_tets)
    v, t, rounds = bisect_region(fld.cage_vertices, fld.cage_tets,
                                 lambda p: signed_distance(selection, p, f"{where}.select"), edge_length)
    out = Field(fld.prims, v, t, notes=list(fld.notes))
    out.rebind()
    note = {"operation": "remesh", "tets_before": before, "tets_after": len(t), "vertices_after": len(v),
            "rounds": rounds, "seconds": round(time.perf_counter() - t0, 3)}
    out.notes.append(note)
    ctx.log(f"remesh: {before} -> {len(t)} tets in {rounds} rounds")
    return out
