"""Which deformation gradient follows a bent or twisted cage better (edit/affine.py, `gradient`)?

For a run's model and cage, the cage vertices are moved by an analytic map φ (twist, bend); each
primitive's affine map x ↦ μ' + A (x − μ) is compared with φ itself on points of its bounding
ellipsoid (centre ± 0.75 of each radius, and 8 diagonal points): error |φ(y) − μ' − A(y − μ)|
in units of the primitive's max radius. Prints mean / 95th percentile / max for the cage gradients
`smooth`, `centre` and `tet` (`map` is the built-in operations' own) without splitting, and each with
and without splitting, also against the cage's own piecewise-linear map (what a primitive can
follow at best).

    OMP_NUM_THREADS=1 .venv/bin/python scripts/edit_gradient_study.py RUN
"""

from __future__ import annotations

import itertools
import math
import sys

import numpy as np
import torch

from radfield.edit.source import load_source
from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.edit import affine
from radfield.edit.warp import axis_rotation


def twist(x, degrees_per_unit=45.0):
    axis = np.array([0.0, 0.0, 1.0])
    return np.einsum("nij,nj->ni", axis_rotation(axis, math.radians(degrees_per_unit) * x[:, 2]), x)


def bend(x, degrees_per_unit=45.0):
    axis, along = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    k = math.radians(degrees_per_unit)
    centre = np.cross(axis, along) / k
    h = x @ along
    return centre + np.einsum("nij,nj->ni", axis_rotation(axis, k * h), x - h[:, None] * along - centre)


def cage_map(fld, new):
    """The piecewise-linear map of the cage itself: y -> Σ λ_i v'_i of the tet holding y."""
    from radfield.core.geometry.cage import bind_to_cage

    def phi(y):
        tet, bary = bind_to_cage(y, (fld.cage_vertices, fld.cage_tets))
        return np.einsum("pk,pkd->pd", bary, new[fld.cage_tets[tet]])
    return phi


def probe_errors(fld, phi, gradient, target=None):
    """Error of each primitive's affine map against `target` (default phi) on its probe points."""
    new = phi(fld.cage_vertices)
    target = target or phi
    a, means, _ = affine.primitive_maps(fld, new, gradient)
    prims = fld.prims
    rot = quat_to_rotmat(prims.quats.double()).numpy()
    s = torch.exp(prims.log_scales.double()).numpy()
    dirs = [np.eye(3)[i] * sign for i in range(3) for sign in (1, -1)]
    dirs += [np.array(c) / math.sqrt(3) for c in itertools.product((1, -1), repeat=3)]
    mu = prims.means.double().numpy()
    errs = []
    for z in dirs:
        y = mu + np.einsum("pij,pj->pi", rot, 0.75 * s * z)
        approx = means + np.einsum("pij,pj->pi", a, y - mu)
        errs.append(np.linalg.norm(target(y) - approx, axis=1) / s.max(1))
    return np.max(errs, 0)


def main(run):
    fld = load_source(run)
    print(f"{run}: {len(fld.prims)} primitives, {len(fld.cage_tets)} tets")
    for name, phi in (("twist 45°/unit about z", twist), ("bend 45°/unit about y along z", bend)):
        for gradient in affine.CAGE_GRADIENTS:
            e = probe_errors(fld, phi, gradient)
            print(f"  {name:30s} {gradient:7s} probe error / max radius: mean {e.mean():.4f}  "
                  f"p95 {np.percentile(e, 95):.4f}  max {e.max():.4f}")
        new = phi(fld.cage_vertices)
        a_tet, _, _ = affine.tet_maps(fld.cage_vertices, new, fld.cage_tets)
        for threshold in (0.25, 1e9):
            split = fld
            for _ in range(affine.MAX_SPLIT_ROUNDS):   # as deform_field splits
                flagged = np.flatnonzero(affine.nonuniformity(split, a_tet) > threshold)
                if flagged.size == 0:
                    break
                split = split.with_prims(affine.split_primitives(split.prims, flagged))
            for gradient in affine.CAGE_GRADIENTS:
                e = probe_errors(split, phi, gradient)
                c = probe_errors(split, phi, gradient, cage_map(fld, new))
                print(f"  {name:30s} {gradient:7s} split at {threshold}: {len(split.prims) - len(fld.prims)} splits; "
                      f"error vs φ mean {e.mean():.4f} p95 {np.percentile(e, 95):.4f}; "
                      f"vs the cage's own map mean {c.mean():.4f} p95 {np.percentile(c, 95):.4f}")


if __name__ == "__main__":
    main(sys.argv[1])
