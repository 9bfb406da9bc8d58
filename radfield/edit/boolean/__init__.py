"""Boolean operations between the edited field E and a shape, a closed mesh or another field F
(Neural Impostor §4.3, eq. 13-15), with local retraining of the primitives on the boundary (§4.2).

    - boolean: {op: difference, shape: {sphere: {center: [x, y, z], radius: r}}}
    - boolean: {op: intersection, shape: {box: {min: [...], max: [...]}}}      # or {center, size, rotate}
    - boolean: {op: difference, shape: {halfspace: {point: [...], normal: [...]}}}   # removes the normal's side
    - boolean: {op: difference, mesh: PATH}                                  # closed PLY / OBJ / STL
    - boolean: {op: union, model: OTHER_RUN_OR_MODEL, epsilon: ε}            # also intersection, difference, xor

Boolean fields: a shape's or mesh's inside (mesh: generalised winding number > 1/2); a field's
B = [D(x) > ε] with D(x) = Σ_i [x ∈ B_i] max(σ_i(x), 0) / max(s_i) (eq. 13; ε defaults to
0.5 / the field's median max(s): one median primitive with σ > 0.5). Eq. 14 becomes a mask on each
field's density (eq. 15), E's taking precedence where both are present:
    difference  E·(1 − B_F)        intersection  E·B_F
    union       E + F·(1 − B_E)    xor           E·(1 − B_F) + F·(1 − B_E)
(union and xor need a field operand: a shape has no radiance to add).

A field's boolean field is sampled once on a grid (spacing a quarter of the straddling
primitives' median radius) over the straddling primitives for the teacher's quadrature.

Each primitive is classified by its mask over its ellipsoid (an exact bounding-sphere test against
the shape's signed distance, exact support-function test for a half-space, else 64 samples:
centre, axis ends, diagonals, random points): wholly kept (bit-identical), wholly removed
(dropped), or straddling. Straddling primitives are retrained locally against the teacher — the
exact boolean field rendered by masked quadrature (retrain.py). A cut (difference or
intersection) through a solid object also gets a cap: new thin disc primitives seeded on the part
of the cut surface that lies inside the object (ray-occupancy test: opacity > 1/2 along at least
12 of 14 directions); the cut surface is sampled for every operand kind — an analytic shape's zero
level set, a mesh's triangles, a field's ε-level set of D marched on a grid —, the discs are
coloured like the densest nearby original primitives; the teacher includes the cap, so the retrained cut
face is closed, not hollow. No analytic clipping of the integration interval (that would need
renderer kernel changes): retraining is the method.

A windowed model (prims.window): σ is the windowed density 1.5 (1 − r²) σ everywhere above (D,
the teacher, retrain.py), the caps are windowed too, and a field operand must have the same window.

One module per phase of the operation (operation.py: `boolean`, which runs them in order):
    operands.py        the operand (shapes.py: analytic shapes and meshes; or a field) and ε
    masks.py           eq. 14 as a mask on each field's density; field masks gridded for the teacher
    classification.py  each primitive kept, dropped or straddling
    caps.py            the cap of a cut face, on the operand's boundary (surface.py)
    retraining.py      the straddling primitives and the caps refitted to the teacher
    gaussian_cut.py    a Gaussian field's straddling Gaussians split, not retrained (no cap)
"""

from radfield.edit.boolean.caps import cap_primitives, cut_caps
from radfield.edit.boolean.classification import SAMPLES, classify, mask_classes
from radfield.edit.boolean.masks import default_epsilon, field_mask, gridded, gridded_masks, operand_masks
from radfield.edit.boolean.operands import Operand, read_operand
from radfield.edit.boolean.operation import OPS, boolean   # importing it registers the `boolean` operation
from radfield.edit.boolean.retraining import density_teacher, retrain_boundary
from radfield.edit.boolean.shapes import Shape, mesh_shape, parse_shape, read_mesh, winding_number
from radfield.edit.boolean.surface import cut_surface, level_set_points, mesh_surface_points, surface_points

__all__ = ["OPS", "SAMPLES", "Operand", "Shape", "boolean", "cap_primitives", "classify", "cut_caps", "cut_surface",
           "default_epsilon", "density_teacher", "field_mask", "gridded", "gridded_masks", "level_set_points",
           "mask_classes", "mesh_shape", "mesh_surface_points", "operand_masks", "parse_shape", "read_mesh",
           "read_operand", "retrain_boundary", "surface_points", "winding_number"]
