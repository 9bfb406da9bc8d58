"""Composition: add another field under a similarity x' = s·R·x + t (R = Rz·Ry·Rx, degrees).

    - compose: {model: OTHER_RUN_OR_MODEL, rotate: [rx, ry, rz], translate: [tx, ty, tz], scale: s}

The other field's primitives are mapped exactly: μ' = sRμ + t, R_prim' = R·R_prim (quaternions
compose), log s' = log s + log(s), and for neural primitives W1' = W1 Rᵀ — with u = (x − μ)/max(s),
u' = (x' − μ')/max(s') = R u for a similarity (the factor s cancels), so σ'(x') = σ(x); optical
depth is measured in units of the primitive's size, so opacities are unchanged too. The SH
coefficients turn with the object (f'(d) = f(Rᵀd), band by band). Cages merge as a disjoint union
(the other's vertices mapped, its tets and bindings offset), so the result stays editable.

A field edited with preserve_opacity carries a per-primitive `rest_metric`; joined with a field
that has none, the other's primitives get the identity metric (their optical depth unchanged).
Mismatched fields: SH degree → the lower one is padded with zero bands; hidden width → the
narrower MLP is padded with zero units (W2 = 0 adds nothing); ω0 → the other's W1 and b1 are
rescaled by ω0_other / ω0 (only ω0·W1 and ω0·b1 enter the density); rays per pixel
(`supersample`) → the larger; Gaussians with neural primitives → refused; a windowed neural field
with a hard-edged one (their `window` differs: one model has one density) → refused. What is
kind-specific here (W1 under the rotation, ω0, the hidden width, the rest metric, the window) is
the kind's (radfield.core.kinds: `rotated`, `harmonise`, `check_combinable`, `combine_notes`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch

from radfield.errors import RadfieldError
from radfield.core import kinds
from radfield.core.geometry.rotations import quat_to_rotmat, rotmat_to_quat
from radfield.core.splat.sh import num_sh_coeffs, rotate_sh
from radfield.edit.field import Field
from radfield.edit.model_operand import load_operand, same_kind
from radfield.edit.select import number, vector
from radfield.edit.spec import check_keys, operation
from radfield.edit.warp import euler_rotation


def similarity(prims, rot: np.ndarray, translate: np.ndarray, scale: float):
    """The primitives mapped exactly by x' = scale·R·x + translate (module docstring)."""
    r = torch.as_tensor(rot, dtype=prims.means.dtype)
    t = torch.as_tensor(translate, dtype=prims.means.dtype)
    out = prims.map(lambda x: x.clone())
    out.means = scale * prims.means @ r.T + t
    out.quats = rotmat_to_quat(r @ quat_to_rotmat(prims.quats))
    out.log_scales = prims.log_scales + math.log(scale)
    out.sh = rotate_sh(prims.sh, rot)
    for name, value in kinds.of(prims).rotated(prims, r).items():   # neural: W1' = W1 Rᵀ
        setattr(out, name, value)
    return out


def pad_sh(prims, degree: int):
    """The primitives with zero SH bands appended up to `degree`."""
    k = num_sh_coeffs(degree)
    if prims.sh.shape[1] >= k:
        return prims
    out = prims.map(lambda x: x)
    out.sh = torch.cat([prims.sh, prims.sh.new_zeros(len(prims), k - prims.sh.shape[1], 3)], 1)
    return out


def concat_prims(a, b, where: str = "compose"):
    """One primitive set holding a's then b's, after padding both to a common layout (SH here,
    the kind's own tensors by its `harmonise`: neural, b's ω0 is folded into its W1 and b1 so the
    result keeps a's ω0)."""
    if a.kind != b.kind:
        raise RadfieldError(f"{where}: cannot combine a {a.kind} model with a {b.kind} model")
    kind = kinds.of(a)
    kind.check_combinable(a, b, where)
    degree = max(a.sh_degree, b.sh_degree)
    a, b = pad_sh(a, degree), pad_sh(b, degree)
    a, b = kind.harmonise(a, b)
    b = b.to(dtype=a.means.dtype)
    # the finer of the two: a model trained at n drawn at n' > n is only a little smoother (box
    # filter), one drawn at fewer rays than it was trained with loses its edges (docs/studies/edges-supersampling.md)
    out = replace(a, supersample=max(a.supersample, b.supersample))
    for name, tensor in a.tensors().items():
        setattr(out, name, torch.cat([tensor, getattr(b, name)], 0))
    return out


def merge_fields(fld: Field, other: Field, where: str) -> Field:
    """fld's primitives and cage followed by other's (already in fld's frame): the cage is the
    disjoint union, other's binding offset by fld's tet count."""
    same_kind(fld, other, where)
    prims = concat_prims(fld.prims, other.prims, where)
    if fld.has_cage and other.has_cage:
        vertices = np.concatenate([fld.cage_vertices, other.cage_vertices])
        tets = np.concatenate([fld.cage_tets, other.cage_tets + len(fld.cage_vertices)])
        tet = np.concatenate([fld.tet, np.where(other.tet >= 0, other.tet + len(fld.cage_tets), -1)])
        bary = np.concatenate([fld.bary, other.bary])
    elif fld.has_cage or other.has_cage:
        # one cage only: it stays; the cage-less part is unbound (tet -1), it follows no deformation
        base = fld if fld.has_cage else other
        vertices, tets = base.cage_vertices, base.cage_tets
        unbound = lambda f: (np.full(len(f.prims), -1, np.int64), np.zeros((len(f.prims), 4)))
        parts = [(f.tet, f.bary) if f is base else unbound(f) for f in (fld, other)]
        tet, bary = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    else:
        vertices = tets = None
        tet, bary = np.full(len(prims), -1, np.int64), np.zeros((len(prims), 4))
    return Field(prims, vertices, tets, tet, bary, notes=list(fld.notes))


def transform_field(fld: Field, rot: np.ndarray, translate: np.ndarray, scale: float) -> Field:
    """The whole field (primitives and cage; binding unchanged) under x' = s·R·x + t."""
    prims = similarity(fld.prims, rot, translate, scale)
    vertices = None if fld.cage_vertices is None else scale * fld.cage_vertices @ rot.T + translate
    return Field(prims, vertices, fld.cage_tets, fld.tet.copy(), fld.bary.copy(), notes=list(fld.notes))


@operation("compose")
def compose(fld: Field, args, ctx) -> Field:
    where = ctx.where
    check_keys(args, {"model", "rotate", "translate", "scale"}, where)
    if "model" not in args:
        raise RadfieldError(f"{where}.model: required (the run or model file to add)")
    rot = euler_rotation(vector(args, "rotate", where)) if "rotate" in args else np.eye(3)
    translate = vector(args, "translate", where) if "translate" in args else np.zeros(3)
    scale = number(args, "scale", where, default=1.0, positive=True)
    other = load_operand(args["model"], "model", ctx)
    same_kind(fld, other, where)
    out = merge_fields(fld, transform_field(other, rot, translate, scale), where)
    note = {"operation": "compose", "model": str(args["model"]), "added": len(other.prims), "total": len(out.prims)}
    note.update(kinds.of(fld.prims).combine_notes(fld.prims, other.prims))
    out.notes.append(note)
    ctx.log(f"compose: added {len(other.prims)} primitives ({len(out.prims)} in all)")
    return out
