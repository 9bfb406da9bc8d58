"""The `boolean` edit operation: its phases in order (the package docstring describes the method)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from radfield.errors import RadfieldError
from radfield.core.geometry.cage import bind_to_cage
from radfield.core import kinds
from radfield.edit.boolean.caps import cut_caps
from radfield.edit.boolean.classification import mask_classes
from radfield.edit.boolean.gaussian_cut import refine_boundary
from radfield.edit.boolean.masks import gridded_masks, operand_masks
from radfield.edit.boolean.operands import read_operand
from radfield.edit.boolean.retraining import retrain_boundary
from radfield.edit.compose import concat_prims, merge_fields
from radfield.edit.field import Field
from radfield.edit.select import number
from radfield.edit.spec import check_keys, operation

OPS = ("union", "intersection", "difference", "xor")
# the timed phases of a boolean, in its note: they partition its wall time `seconds`. teacher,
# stage1 and stage2 are timed inside the retraining; retrain_other is the rest of it (the density
# samples, the cameras, the PSNR renders before and after); other: what no phase measures (assembly)
PHASES = ("operand_seconds", "classify_seconds", "cap_seconds", "mask_grid_seconds", "teacher_seconds",
          "stage1_seconds", "stage2_seconds", "retrain_other_seconds", "other_seconds")
ARGUMENTS = {"op", "shape", "mesh", "model", "epsilon", "rotate", "translate", "scale", "steps", "views", "size", "cap"}


@dataclass
class Options:
    """A boolean entry's settings: op, the operand's key (shape, mesh or model), the retraining's
    steps per stage, its views and their size in pixels, whether a cut gets a cap."""
    op: str
    operand: str
    steps: int
    views: int
    size: int
    cap: bool


@dataclass
class Split:
    """The primitives of `base` (E, or E then F when F's primitives take part) by class: kept
    (bit-identical), straddling (retrained, each with its part's mask: mask_id into masks, −1 for
    the others), the rest dropped."""
    base: Field
    kept: np.ndarray
    straddle: np.ndarray
    dropped: int
    mask_id: np.ndarray
    masks: list


@operation("boolean")
def boolean(fld: Field, args, ctx) -> Field:
    """E op operand (package docstring): read the entry, classify the primitives by their masks,
    cap a cut, retrain the straddling primitives (and the cap) against the teacher, assemble; a
    Gaussian field's straddling primitives are split instead (gaussian_cut.py)."""
    opts = read_options(fld, args, ctx.where)
    t0 = time.perf_counter()
    operand = read_operand(fld, args, opts.op, ctx)
    parts = operand_masks(fld, operand.shape, operand.other, opts.op, operand.epsilon, operand.epsilon_e)
    t1 = time.perf_counter()
    split = split_primitives(parts, operand, opts.op, ctx.where)
    prims, kept, straddle = split.base.prims, split.kept, split.straddle
    straddlers = prims.select(torch.as_tensor(straddle))
    note = {"operation": "boolean", "op": opts.op, "operand": opts.operand, "kept": int(kept.size),
            "dropped": split.dropped, "retrained": int(straddle.size), "seeded": 0,
            "operand_seconds": round(t1 - t0, 2)}
    t2 = time.perf_counter()
    note["classify_seconds"] = round(t2 - t1, 2)

    if kinds.of(prims).exact_gaussians:   # Gaussians: the boundary split, not retrained (gaussian_cut.py)
        return _assemble(fld, split, cut_gaussians(split, operand.shape, opts.op, note), note, t0, ctx.log)
    caps = prims.select(torch.zeros(0, dtype=torch.int64))
    if opts.cap and straddle.size and opts.op in ("difference", "intersection"):
        # the cut face: the operand's boundary where it lies inside E (union and xor add F's own surface)
        caps = cut_caps(fld.prims, straddlers, operand.shape, operand.other, operand.epsilon, opts.op, ctx.seed)
        note["seeded"] = len(caps)
    note["cap_seconds"] = round(time.perf_counter() - t2, 2)

    masks = split.masks
    if operand.shape is None and straddle.size:
        masks = gridded_masks(masks, straddlers, note)

    frozen = prims.select(torch.as_tensor(kept))
    if straddle.size == 0 and len(caps) == 0:
        out_prims = frozen
    else:
        t3 = time.perf_counter()
        out_prims = retrain_boundary(frozen, straddlers, caps, split.mask_id[straddle], masks,
                                     opts.steps, opts.views, opts.size, ctx, note)
        inside = sum(float(note.get(key, 0.0)) for key in ("teacher_seconds", "stage1_seconds", "stage2_seconds"))
        note["retrain_other_seconds"] = round(max(time.perf_counter() - t3 - inside, 0.0), 2)
    return _assemble(fld, split, out_prims, note, t0, ctx.log)


def cut_gaussians(split: Split, shape, op: str, note: dict):
    """The kept Gaussians, then the straddling ones refined against their masks (gaussian_cut.py);
    the splits made and the boundary Gaussians kept go in `note`."""
    prims = split.base.prims
    out = prims.select(torch.as_tensor(split.kept))
    note.update(retrained=0, straddling=int(split.straddle.size), splits=0, boundary_kept=0)
    for k, mask in enumerate(split.masks):
        ids = split.straddle[split.mask_id[split.straddle] == k]
        if ids.size:
            refined, figures = refine_boundary(prims.select(torch.as_tensor(ids)), mask, shape, op == "intersection")
            out = concat_prims(out, refined)
            note.update({key: note[key] + value for key, value in figures.items()})
    return out


def _assemble(fld: Field, split: Split, out_prims, note: dict, t0: float, log) -> Field:
    """The edited field (result_field) with the boolean's note, its phases adding up to its seconds
    (logged)."""
    out = result_field(fld, split.base, split.kept, out_prims)
    seconds = round(time.perf_counter() - t0, 2)
    # the phases add up to `seconds` (to the rounding): what no phase measured is `other`
    for key in PHASES[:-1]:   # in PHASES' order, after the other figures
        note[key] = round(float(note.pop(key, 0.0)), 2)
    note["other_seconds"] = round(max(seconds - sum(note[key] for key in PHASES[:-1]), 0.0), 2)
    note["seconds"] = seconds
    out.notes.append(note)
    log(f"boolean {note['op']}: {note}")
    return out


def read_options(fld: Field, args, where: str) -> Options:
    """The entry's settings, every mistake a one-line RadfieldError at `where`."""
    check_keys(args, ARGUMENTS, where)
    op = args.get("op")
    if op not in OPS:
        raise RadfieldError(f"{where}.op: expected one of {', '.join(OPS)}, got {op!r}")
    given = [k for k in ("shape", "mesh", "model") if k in args]
    if len(given) != 1:
        raise RadfieldError(f"{where}: give exactly one operand: shape, mesh or model (got {given or 'none'})")
    steps = int(number(args, "steps", where, default=150, positive=True))
    views = int(number(args, "views", where, default=16, positive=True))
    size = int(number(args, "size", where, default=48, positive=True))
    cap = args.get("cap", True)
    if not isinstance(cap, bool):
        raise RadfieldError(f"{where}.cap: expected true or false, got {cap!r}")
    kind = kinds.of(fld.prims)
    if not (kind.retrainable_locally or kind.exact_gaussians):
        raise RadfieldError(f"{where}: boolean operations need a neural-primitive or a 3D Gaussian model, not {kind.name}")
    if kind.exact_gaussians and given[0] == "model":
        raise RadfieldError(f"{where}: a Gaussian field is cut by a shape or a mesh (a model operand's boolean field needs "
                            f"neural densities)")
    if any(k in args for k in ("rotate", "translate", "scale")) and "model" not in args:
        raise RadfieldError(f"{where}: rotate/translate/scale place a model operand; shapes take their own coordinates")
    return Options(op, given[0], steps, views, size, cap)


def split_primitives(parts: list, operand, op: str, where: str) -> Split:
    """Classify each part's primitives by its mask (a solid operand's signed distance settles most
    of E's) and join the parts into one field."""
    keep_inside = op == "intersection"
    classified = [(f, m, mask_classes(f.prims, m, operand.shape, keep_inside)) for f, m in parts]
    base = classified[0][0] if len(classified) == 1 else merge_fields(classified[0][0], classified[1][0], where)
    classes = np.concatenate([c for _, _, c in classified])
    mask_id = np.concatenate([np.where(c == -1, k, -1) for k, (_, _, c) in enumerate(classified)])
    return Split(base, np.flatnonzero(classes == 1), np.flatnonzero(classes == -1), int((classes == 0).sum()),
                 mask_id, [m for _, m, _ in classified])


def result_field(fld: Field, base: Field, kept: np.ndarray, out_prims) -> Field:
    """The edited field: out_prims (kept ones first) in base's cage, the kept primitives keeping
    their binding, the new ones bound to the cage where there is one; fld's notes so far."""
    tet = np.concatenate([base.tet[kept], np.full(len(out_prims) - kept.size, -1)])
    bary = np.concatenate([base.bary[kept], np.zeros((len(out_prims) - kept.size, 4))])
    out = Field(out_prims, base.cage_vertices, base.cage_tets, tet, bary, notes=list(fld.notes))
    if out.has_cage and len(out_prims) > kept.size:
        new = np.arange(kept.size, len(out_prims))
        out.tet[new], out.bary[new] = bind_to_cage(out_prims.means[new].detach().cpu().double().numpy(), (out.cage_vertices, out.cage_tets))
    return out
