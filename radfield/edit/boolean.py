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
"""

from __future__ import annotations

import contextlib
import io
import math
import time
from collections.abc import Mapping

import numpy as np
import torch
from scipy.spatial import cKDTree

from radfield.errors import RadfieldError
from radfield.core.kinds.primitives import NeuralPrimitives, quat_to_rotmat, rotmat_to_quat
from radfield.core.render.sh import rgb_to_sh_dc, sh_to_color
from radfield.edit import retrain
from radfield.edit.compose import merge_fields, transform_field
from radfield.edit.warp import euler_rotation
from radfield.edit.field import Field
from radfield.edit.operand import load_operand, same_kind
from radfield.edit.recolor import peak_density
from radfield.edit.select import number, vector
from radfield.edit.spec import check_keys, operation

OPS = ("union", "intersection", "difference", "xor")
SAMPLES = 64


# --- operands --------------------------------------------------------------------------------

class Shape:
    """An analytic solid: signed distance sd(x) (negative inside, 1-Lipschitz) and inside(x)."""

    def __init__(self, kind: str, sd, exact_extent=None):
        self.kind, self.sd, self.exact_extent = kind, sd, exact_extent
        self.mesh = None   # (vertices, triangles) of a mesh operand

    def inside(self, points: np.ndarray) -> np.ndarray:
        return self.sd(points) <= 0


def parse_shape(spec, where: str) -> Shape:
    if not isinstance(spec, Mapping) or len(spec) != 1:
        raise RadfieldError(f"{where}: a shape is one of {{sphere: ...}}, {{box: ...}}, {{halfspace: ...}}, got {spec!r}")
    (kind, args), = spec.items()
    w = f"{where}.{kind}"
    if not isinstance(args, Mapping):
        raise RadfieldError(f"{w}: expected a mapping of its parameters, got {args!r}")
    if kind == "sphere":
        check_keys(args, {"center", "radius"}, w)
        c, r = vector(args, "center", w), number(args, "radius", w, positive=True)
        return Shape("sphere", lambda p: np.linalg.norm(p - c, axis=1) - r)
    if kind == "halfspace":
        check_keys(args, {"point", "normal"}, w)
        point, normal = vector(args, "point", w), vector(args, "normal", w)
        if np.linalg.norm(normal) == 0:
            raise RadfieldError(f"{w}.normal: must not be zero")
        n = normal / np.linalg.norm(normal)
        # inside = the side the normal points to; an ellipsoid's extent along n is |S Rᵀ n| (exact)
        return Shape("halfspace", lambda p: -(p - point) @ n, exact_extent=n)
    if kind == "box":
        if "min" in args or "max" in args:
            check_keys(args, {"min", "max"}, w)
            lo, hi = vector(args, "min", w), vector(args, "max", w)
            if not (lo < hi).all():
                raise RadfieldError(f"{w}: min must be below max on every axis, got {lo.tolist()} and {hi.tolist()}")
            centre, half, rot = (lo + hi) / 2, (hi - lo) / 2, np.eye(3)
        else:
            check_keys(args, {"center", "size", "rotate"}, w)
            centre, size = vector(args, "center", w), vector(args, "size", w)
            if not (size > 0).all():
                raise RadfieldError(f"{w}.size: must be positive on every axis, got {size.tolist()}")
            half = size / 2
            rot = euler_rotation(vector(args, "rotate", w)) if "rotate" in args else np.eye(3)

        def sd(p):
            q = np.abs((p - centre) @ rot) - half
            return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)
        return Shape("box", sd)
    raise RadfieldError(f"{where}: unknown shape {kind!r} (expected sphere, box, halfspace)")


def read_mesh(path, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and triangles (F, 3) of a closed PLY / OBJ / STL mesh."""
    import meshio

    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            mesh = meshio.read(path)
    except (Exception, SystemExit) as exc:  # meshio raises many types (and may exit) on bad files
        raise RadfieldError(f"{where}: {path} is not a readable mesh ({type(exc).__name__})") from None
    tris = [c.data for c in mesh.cells if c.type == "triangle"]
    quads = [c.data for c in mesh.cells if c.type == "quad"]
    faces = tris + [q[:, [0, 1, 2]] for q in quads] + [q[:, [0, 2, 3]] for q in quads]
    if not faces:
        raise RadfieldError(f"{where}: {path} has no triangles")
    return np.asarray(mesh.points, np.float64)[:, :3], np.concatenate(faces).astype(np.int64)


def winding_number(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """Generalised winding number (Jacobson et al. 2013): Σ solid angles / 4π of the triangles seen
    from each point (van Oosterom-Strackee); ≈ 1 inside a closed mesh, 0 outside, robust to small holes."""
    tri = vertices[faces]                                              # (F, 3, 3)
    out = np.zeros(len(points))
    for lo in range(0, len(points), chunk):
        a, b, c = (tri[None, :, k] - points[lo:lo + chunk, None] for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
        out[lo:lo + chunk] = 2 * np.arctan2(det, den).sum(1) / (4 * math.pi)
    return out


def mesh_shape(path, where: str) -> Shape:
    v, f = read_mesh(path, where)
    lo, hi = v.min(0), v.max(0)

    def inside(p):
        out = np.zeros(len(p), bool)
        near = np.all((p >= lo) & (p <= hi), axis=1)   # nothing outside the bounding box is inside
        if near.any():
            out[near] = np.abs(winding_number(v, f, p[near])) > 0.5
        return out
    shape = Shape("mesh", None)
    shape.inside = inside
    shape.mesh = (v, f)
    return shape


def default_epsilon(prims) -> float:
    return 0.5 / float(prims.scales.amax(-1).median()) if len(prims) else 1.0


def field_mask(fld: Field, epsilon: float):
    """B = [D > ε] of a field, as a function of points (n, 3)."""
    return lambda points: retrain.field_density(fld.prims, points) > epsilon


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


# --- classification --------------------------------------------------------------------------

def classify(prims, keep_fn, shape: Shape | None = None, keep_inside: bool = True) -> np.ndarray:
    """Per primitive: 1 mask is 1 on its whole ellipsoid (kept), 0 wholly 0 (dropped), -1 straddling.
    keep_fn maps points -> bool (the mask). With a shape, the bounding-sphere test on its signed
    distance (exact, 1-Lipschitz) settles most primitives before sampling; keep_inside says
    whether the mask is the shape's inside or its outside."""
    n = len(prims)
    out = np.full(n, -2)
    means = prims.means.detach().cpu().double().numpy()
    reach = prims.scales.detach().cpu().double().amax(-1).numpy()
    if shape is not None and shape.sd is not None:
        d = shape.sd(means)
        if shape.exact_extent is not None:
            rot = quat_to_rotmat(prims.quats.detach().cpu().double()).numpy()
            reach = np.linalg.norm(np.einsum("pji,j->pi", rot, shape.exact_extent) * np.exp(prims.log_scales.detach().cpu().double().numpy()), axis=1)
        inside_all, outside_all = d <= -reach, d >= reach
        out[inside_all] = 1 if keep_inside else 0
        out[outside_all] = 0 if keep_inside else 1
    todo = np.flatnonzero(out == -2)
    if todo.size:
        pts = retrain.ellipsoid_points(prims.select(torch.as_tensor(todo)).to(dtype=torch.float64).map(lambda t: t.detach().cpu()),
                                       retrain.unit_ball_samples(SAMPLES)).numpy()
        m = keep_fn(pts.reshape(-1, 3)).reshape(len(todo), SAMPLES)
        out[todo] = np.where(m.all(1), 1, np.where(~m.any(1), 0, -1))
    return out


# --- the cap of a cut face -------------------------------------------------------------------

def _sphere_directions(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def _thin(points: np.ndarray, normals: np.ndarray, spacing: float):
    """One point (and its normal) per cell of side `spacing`."""
    if len(points) == 0:
        return points, normals
    _, first = np.unique(np.floor(points / spacing).astype(np.int64), axis=0, return_index=True)
    first = np.sort(first)
    return points[first], normals[first]


def _in_box(points: np.ndarray, lo, hi) -> np.ndarray:
    return np.all((points >= lo) & (points <= hi), axis=1)


def surface_points(shape: Shape, lo: np.ndarray, hi: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points about `spacing` apart on an analytic shape's surface inside the box [lo, hi] and the
    outward normals there: a grid of the box projected onto the zero level set of the signed
    distance (Newton steps along its gradient)."""
    axes = [np.arange(a, b + spacing, spacing) for a, b in zip(lo, hi)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    grid = grid[np.abs(shape.sd(grid)) < spacing]
    for _ in range(4):
        g = _gradient(shape.sd, grid)
        grid = grid - shape.sd(grid)[:, None] * g
    grid = grid[np.abs(shape.sd(grid)) < 1e-3 * spacing]
    return _thin(grid, _gradient(shape.sd, grid), spacing)


def mesh_surface_points(shape: Shape, lo: np.ndarray, hi: np.ndarray, spacing: float, seed: int = 0):
    """Points about `spacing` apart on a mesh operand's triangles inside the box [lo, hi], and the
    outward normals there: area-weighted samples of the triangles that meet the box (about
    2·area/spacing² per triangle), thinned to one per cell; a triangle normal is flipped where a
    step along it enters the mesh (winding number), so a mesh whose triangles face inwards works too."""
    v, f = shape.mesh
    tri = v[f]                                                        # (F, 3, 3)
    meets = np.all((tri.max(1) >= lo) & (tri.min(1) <= hi), axis=1)
    tri = tri[meets]
    empty = np.zeros((0, 3))
    if len(tri) == 0:
        return empty, empty
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    keep = area > 0
    tri, cross, area = tri[keep], cross[keep], area[keep]
    count = 2 * area / spacing**2
    count = np.ceil(count * min(1.0, 1e6 / max(count.sum(), 1.0))).astype(np.int64)   # at most ~10⁶ samples
    owner = np.repeat(np.arange(len(tri)), count)
    rng = np.random.default_rng(seed)
    r1, r2 = np.sqrt(rng.random(len(owner))), rng.random(len(owner))   # uniform on a triangle
    points = ((1 - r1)[:, None] * tri[owner, 0] + (r1 * (1 - r2))[:, None] * tri[owner, 1]
              + (r1 * r2)[:, None] * tri[owner, 2])
    normals = cross[owner] / (2 * area[owner, None])
    inside = _in_box(points, lo, hi)
    points, normals = _thin(points[inside], normals[inside], spacing)
    if len(points):
        flip = shape.inside(points + 0.1 * spacing * normals)
        normals[flip] = -normals[flip]
    return points, normals


def level_set_points(fld: Field, epsilon: float, lo: np.ndarray, hi: np.ndarray, spacing: float,
                     max_points: int = 120_000):
    """Points about `spacing` apart on a field operand's boundary D = ε inside [lo, hi] and the
    outward normals −∇D/|∇D| there: D sampled on a grid (spacing/2, coarsened to at most max_points
    nodes), each grid edge whose ends lie on both sides of ε gives the linearly interpolated
    crossing, the normal from the grid's central-difference gradient at its nearer end."""
    h = spacing / 2
    while np.prod(np.ceil((hi - lo) / h) + 1) > max_points:
        h *= 1.25
    shape = (np.ceil((hi - lo) / h) + 1).astype(int)
    axes = [lo[i] + h * np.arange(shape[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    d = retrain.field_density(fld.prims, grid.reshape(-1, 3)).reshape(shape)
    grad = np.stack(np.gradient(d, h), -1)
    points, normals = [], []
    for axis in range(3):
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[axis], b[axis] = slice(0, -1), slice(1, None)
        d0, d1 = d[tuple(a)], d[tuple(b)]
        cross = (d0 > epsilon) != (d1 > epsilon)
        if not cross.any():
            continue
        t = (epsilon - d0[cross]) / (d1[cross] - d0[cross])
        p0, p1 = grid[tuple(a)][cross], grid[tuple(b)][cross]
        g = np.where((t < 0.5)[:, None], grad[tuple(a)][cross], grad[tuple(b)][cross])
        points.append(p0 + t[:, None] * (p1 - p0))
        normals.append(-g)
    if not points:
        return np.zeros((0, 3)), np.zeros((0, 3))
    points, normals = np.concatenate(points), np.concatenate(normals)
    ok = np.linalg.norm(normals, axis=1) > 0
    normals = normals[ok] / np.linalg.norm(normals[ok], axis=1, keepdims=True)
    return _thin(points[ok], normals, spacing)


def _gradient(sd, p: np.ndarray, h: float = 1e-5) -> np.ndarray:
    g = np.stack([(sd(p + h * e) - sd(p - h * e)) / (2 * h) for e in np.eye(3)], -1)
    return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)


def cap_primitives(original: NeuralPrimitives, pts: np.ndarray, normal: np.ndarray, spacing: float,
                   seed: int = 0) -> NeuralPrimitives:
    """Thin opaque discs at the cut-surface points `pts` (n, 3) that lie inside the original object,
    facing `normal` (n, 3), the unit normals into the kept region, coloured like the nearest
    original primitives."""
    empty = original.select(torch.zeros(0, dtype=torch.int64))
    if len(pts) == 0:
        return empty
    dirs = _sphere_directions(14)
    occ = retrain.opacity_from(original, np.repeat(pts, 14, 0), np.tile(dirs, (len(pts), 1))).reshape(len(pts), 14)
    solid = (occ > 0.5).sum(1) >= 12
    pts, normal = pts[solid], normal[solid]
    if len(pts) == 0:
        return empty
    radius, thick = 0.8 * spacing, 0.25 * spacing
    # rotation taking z to the normal
    z = torch.as_tensor(normal)
    helper = torch.where((z[:, :1].abs() < 0.9), torch.tensor([[1.0, 0, 0]], dtype=torch.float64), torch.tensor([[0, 1.0, 0]], dtype=torch.float64))
    x = torch.nn.functional.normalize(torch.linalg.cross(helper, z), dim=-1)
    y = torch.linalg.cross(z, x)
    rot = torch.stack([x, y, z], -1)
    means = torch.as_tensor(pts + thick * normal)
    # optical depth across the disc at normal incidence: b2 · 2·thick / radius = 3 (α ≈ 0.95; the
    # same through the centre of a windowed disc, whose gain 1.5 keeps the central chord's depth)
    b2 = 3.0 * radius / (2 * thick)
    # colour: per-channel median over the 4 densest of the 16 nearest original primitives (robust
    # to the faint dark floaters a reconstruction keeps inside objects)
    k = min(16, len(original))
    _, near = cKDTree(original.means.detach().cpu().double().numpy()).query(pts, k=k)
    near = torch.as_tensor(near.reshape(len(pts), k))
    densest = torch.argsort(peak_density(original)[near], dim=1, descending=True)[:, :4]
    near, k = torch.gather(near, 1, densest), densest.shape[1]
    view = torch.nn.functional.normalize(-torch.as_tensor(normal), dim=-1)
    colours = sh_to_color(original.sh[near.reshape(-1)].detach().double(), view.repeat_interleave(k, 0), 0)
    colour = colours.reshape(len(pts), k, 3).median(1).values
    g = torch.Generator().manual_seed(seed)
    n, hidden = len(pts), original.hidden
    sh = torch.zeros(n, original.sh.shape[1], 3, dtype=torch.float64)
    sh[:, 0] = rgb_to_sh_dc(colour)
    dtype = original.means.dtype
    return NeuralPrimitives(
        means=means, log_scales=torch.log(torch.tensor([radius, radius, thick], dtype=torch.float64)).expand(n, 3).clone(),
        quats=rotmat_to_quat(rot), sh=sh,
        w1=(torch.rand(n, hidden, 3, generator=g, dtype=torch.float64) * 2 - 1) / 3,
        b1=(torch.rand(n, hidden, generator=g, dtype=torch.float64) * 2 - 1) / 3,
        w2=torch.zeros(n, hidden, dtype=torch.float64), b2=torch.full((n,), b2, dtype=torch.float64),
        omega0=original.omega0, supersample=original.supersample, window=original.window,
    ).to(dtype=dtype)


# --- the operation ---------------------------------------------------------------------------

@operation("boolean")
def boolean(fld: Field, args, ctx) -> Field:
    where = ctx.where
    check_keys(args, {"op", "shape", "mesh", "model", "epsilon", "rotate", "translate", "scale",
                      "steps", "views", "size", "cap"}, where)
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
    if not isinstance(fld.prims, NeuralPrimitives):
        raise RadfieldError(f"{where}: boolean operations need a neural-primitive model (Gaussians have no line-integral density to mask)")
    if any(k in args for k in ("rotate", "translate", "scale")) and "model" not in args:
        raise RadfieldError(f"{where}: rotate/translate/scale place a model operand; shapes take their own coordinates")

    t0 = time.perf_counter()
    other = None
    shape = None
    if "shape" in args:
        shape = parse_shape(args["shape"], f"{where}.shape")
    elif "mesh" in args:
        shape = mesh_shape(ctx.path(args["mesh"], "mesh"), f"{where}.mesh")
    if shape is not None and op in ("union", "xor"):
        raise RadfieldError(f"{where}.op: {op} needs a model operand (a shape has no radiance to add); use difference or intersection")
    if "model" in args:
        other = load_operand(args["model"], "model", ctx)
        same_kind(fld, other, where)
        if any(k in args for k in ("rotate", "translate", "scale")):
            rot = euler_rotation(vector(args, "rotate", where)) if "rotate" in args else np.eye(3)
            other = transform_field(other, rot, vector(args, "translate", where) if "translate" in args else np.zeros(3),
                                    number(args, "scale", where, default=1.0, positive=True))
    epsilon = number(args, "epsilon", where, default=default_epsilon(other.prims if other is not None else fld.prims), positive=True)

    # masks per field (eq. 14 as masks on density, module docstring)
    if shape is not None:
        inside = shape.inside
        keep_inside = op == "intersection"
        e_mask = inside if keep_inside else (lambda p: ~inside(p))
        e_class = classify(fld.prims, e_mask, shape, keep_inside)
        parts = [(fld, e_mask, e_class)]
    else:
        b_f = field_mask(other, epsilon)
        b_e = field_mask(fld, default_epsilon(fld.prims) if "epsilon" not in args else epsilon)
        not_f, not_e = (lambda p: ~b_f(p)), (lambda p: ~b_e(p))
        e_mask = {"difference": not_f, "intersection": b_f, "union": None, "xor": not_f}[op]
        f_mask = {"difference": None, "intersection": None, "union": not_e, "xor": not_e}[op]
        e_class = np.ones(len(fld.prims), int) if e_mask is None else classify(fld.prims, e_mask)
        parts = [(fld, e_mask, e_class)]
        if f_mask is not None:
            parts.append((other, f_mask, classify(other.prims, f_mask)))

    # assemble: kept primitives bit-identical, straddling ones to retrain
    base = parts[0][0] if len(parts) == 1 else merge_fields(parts[0][0], parts[1][0], where)
    classes = np.concatenate([c for _, _, c in parts])
    mask_id = np.concatenate([np.where(c == -1, k, -1) for k, (_, _, c) in enumerate(parts)])
    masks = [m for _, m, _ in parts]
    prims = base.prims
    kept, straddle = np.flatnonzero(classes == 1), np.flatnonzero(classes == -1)
    note = {"operation": "boolean", "op": op, "operand": next(iter(given)), "kept": int(kept.size),
            "dropped": int((classes == 0).sum()), "retrained": int(straddle.size), "seeded": 0}

    caps = prims.select(torch.zeros(0, dtype=torch.int64))
    if cap and straddle.size and op in ("difference", "intersection"):
        # the cut face: the operand's boundary where it lies inside E (union and xor add F's own surface)
        sp = prims.select(torch.as_tensor(straddle))
        reach = sp.scales.detach().amax(-1)
        lo = (sp.means.detach() - reach[:, None]).amin(0).double().numpy()
        hi = (sp.means.detach() + reach[:, None]).amax(0).double().numpy()
        spacing = float(reach.median())
        if shape is not None and shape.sd is not None:
            pts, outward = surface_points(shape, lo, hi, spacing)
        elif shape is not None:
            pts, outward = mesh_surface_points(shape, lo, hi, spacing, ctx.seed)
        else:
            pts, outward = level_set_points(other, epsilon, lo, hi, spacing)
        inward = op == "intersection"                                  # the kept side is the operand's inside
        caps = cap_primitives(fld.prims, pts, -outward if inward else outward, spacing, seed=ctx.seed)
        note["seeded"] = len(caps)

    if shape is None and straddle.size:
        # field masks: sample each boolean field once on a grid over the straddling primitives
        sp = prims.select(torch.as_tensor(straddle)).map(lambda t: t.detach().cpu().double())
        reach = sp.scales.amax(-1)
        lo, hi = (sp.means - reach[:, None]).amin(0).numpy(), (sp.means + reach[:, None]).amax(0).numpy()
        t1 = time.perf_counter()
        grids = [None if m is None else gridded(m, lo, hi, float(reach.median()) / 4) for m in masks]
        masks = [None if g is None else g[0] for g in grids]
        note["mask_grid_spacing"] = round(max(g[1] for g in grids if g is not None), 5)
        note["mask_grid_seconds"] = round(time.perf_counter() - t1, 2)

    frozen = prims.select(torch.as_tensor(kept))
    if straddle.size == 0 and len(caps) == 0:
        out_prims = frozen
    else:
        straddlers = prims.select(torch.as_tensor(straddle))
        from radfield.edit.compose import concat_prims
        student = concat_prims(straddlers, caps)
        teacher = concat_prims(concat_prims(frozen, straddlers), caps)
        t_mask = np.concatenate([np.full(len(frozen), -1), mask_id[straddle], np.full(len(caps), -1)])
        pts, target = _density_teacher(student, len(straddlers), mask_id[straddle], masks, ctx.seed)
        cameras = retrain.orbit_around(student, np.arange(len(student)), views, size)
        t1 = time.perf_counter()
        targets = [retrain.teacher_render(teacher, cam, t_mask, masks) for cam in cameras]
        note["teacher_seconds"] = round(time.perf_counter() - t1, 2)
        ctx.log(f"boolean {op}: kept {kept.size}, dropped {note['dropped']}, retraining {straddle.size} + {len(caps)} seeded")
        fitted, figures = retrain.retrain(frozen, student, pts, target, cameras, targets, steps1=steps, steps2=steps,
                                          seed=ctx.seed, log=ctx.log)
        out_prims = concat_prims(frozen, fitted.to(dtype=frozen.means.dtype))
        note.update({k: round(v, 3) if isinstance(v, float) else v for k, v in figures.items()})
    tet = np.concatenate([base.tet[kept], np.full(len(out_prims) - kept.size, -1)])
    bary = np.concatenate([base.bary[kept], np.zeros((len(out_prims) - kept.size, 4))])
    out = Field(out_prims, base.cage_vertices, base.cage_tets, tet, bary, notes=list(fld.notes))
    if out.has_cage and len(out_prims) > kept.size:
        from radfield.core.geometry.cage import bind_to_cage
        new = np.arange(kept.size, len(out_prims))
        out.tet[new], out.bary[new] = bind_to_cage(out_prims.means[new].detach().cpu().double().numpy(), (out.cage_vertices, out.cage_tets))
    note["seconds"] = round(time.perf_counter() - t0, 2)
    out.notes.append(note)
    ctx.log(f"boolean {op}: {note}")
    return out


def _density_teacher(student: NeuralPrimitives, n_masked: int, mask_ids, masks, seed: int, per_prim: int = 48):
    """Points in the student's ellipsoids and the teacher's density there: Σ over the masked
    (straddling) primitives of m(x)·σ/max s, plus the cap primitives' own density (eq. 15)."""
    u = retrain.unit_ball_samples(per_prim, seed + 1)
    s64 = student.to(dtype=torch.float64).map(lambda t: t.detach())
    pts = retrain.ellipsoid_points(s64, u).reshape(-1, 3)
    target = torch.zeros(len(pts), dtype=torch.float64)
    with torch.no_grad():
        for lo in range(0, len(pts), 2048):
            x = pts[lo:lo + 2048]
            dens = retrain.pair_density(s64, x)                             # (Q, S)
            weight = torch.ones_like(dens)
            for k in np.unique(mask_ids).tolist():
                cols = torch.as_tensor(np.flatnonzero(mask_ids == k))
                m = torch.as_tensor(masks[k](x.numpy()), dtype=torch.float64)
                weight[:, cols] = m[:, None]
            target[lo:lo + 2048] = (dens * weight).sum(1)
    return pts, target
