"""Boolean fields as masks on density (Neural Impostor eq. 13-15): a field's B = [D > ε], the
mask each field's density gets for an operation (eq. 14), and masks sampled once on a grid."""

from __future__ import annotations

import time

import numpy as np

from radfield.core.kinds import neural_density

from radfield.edit.field import Field


def default_epsilon(prims) -> float:
    """ε of a field's boolean field by default: 0.5 / its median max(s), one median primitive with σ > 0.5."""
    return 0.5 / float(prims.scales.amax(-1).median()) if len(prims) else 1.0


def field_mask(fld: Field, epsilon: float):
    """B = [D > ε] of a field, as a function of points (n, 3)."""
    return lambda points: neural_density.field_density(fld.prims, points) > epsilon


def gridded(mask, lo: np.ndarray, hi: np.ndarray, spacing: float, max_points: int = 300_000):
    """`mask` sampled once on a grid over [lo, hi] and looked up at the nearest grid point (points
    outside the grid are evaluated directly): the teacher's quadrature evaluates a field's boolean
    field at millions of ray samples, the grid at ≤ 3·10⁵ points. Resolution: `spacing`, coarsened
    until the grid has at most max_points."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    while np.prod(np.ceil((hi - lo) / spacing) + 1) > max_points:
        spacing *= 1.25
    shape = (np.ceil((hi - lo) / spacing) + 1).astype(int)
    axes = [lo[i] + spacing * np.arange(shape[i]) for i in range(3)]
    grid = mask(np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)).reshape(shape)

    def lookup(points):
        ijk = np.rint((points - lo) / spacing).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < shape), axis=1)
        out = np.empty(len(points), bool)
        out[inside] = grid[tuple(ijk[inside].T)]
        if (~inside).any():
            out[~inside] = mask(points[~inside])
        return out
    return lookup, spacing


def operand_masks(fld: Field, shape, other: Field | None, op: str, epsilon: float, epsilon_e: float) -> list:
    """Eq. 14 as masks on each field's density, E's taking precedence where both are present:
    [(E, m_E)] or, when F's primitives take part (union, xor), [(E, m_E), (F, m_F)]; a mask maps
    points (n, 3) -> bool (n,), None where it is 1 everywhere. A solid operand (`shape`) masks E by
    its inside or outside; a field operand F by B_F = [D_F > ε] (and F by 1 − B_E, B_E at epsilon_e)."""
    if shape is not None:
        inside = shape.inside
        e_mask = inside if op == "intersection" else (lambda p: ~inside(p))
        return [(fld, e_mask)]
    b_f = field_mask(other, epsilon)
    b_e = field_mask(fld, epsilon_e)
    not_f, not_e = (lambda p: ~b_f(p)), (lambda p: ~b_e(p))
    e_mask = {"difference": not_f, "intersection": b_f, "union": None, "xor": not_f}[op]
    f_mask = {"difference": None, "intersection": None, "union": not_e, "xor": not_e}[op]
    return [(fld, e_mask)] + ([(other, f_mask)] if f_mask is not None else [])


def gridded_masks(masks: list, straddlers, note: dict) -> list:
    """Field masks sampled once on a grid over the straddling primitives (spacing a quarter of
    their median radius) for the teacher's quadrature; the grid's spacing and seconds go in `note`."""
    sp = straddlers.map(lambda t: t.detach().cpu().double())
    reach = sp.scales.amax(-1)
    lo, hi = (sp.means - reach[:, None]).amin(0).numpy(), (sp.means + reach[:, None]).amax(0).numpy()
    t1 = time.perf_counter()
    grids = [None if m is None else gridded(m, lo, hi, float(reach.median()) / 4) for m in masks]
    note["mask_grid_spacing"] = round(max(g[1] for g in grids if g is not None), 5)
    note["mask_grid_seconds"] = round(time.perf_counter() - t1, 2)
    return [None if g is None else g[0] for g in grids]
