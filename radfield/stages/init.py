"""Stage "init": the primitives training starts from, written as a model file in the world frame.

Centres come from `init.source`: `mesh` (uniform samples over the area of the dataset's mesh.ply,
as the paper resamples its meshes; the vertices for a point cloud), `points` (SfM points),
`triangulate` (the triangulate stage's points: features of a posed dataset without points, such as
fern's transforms.json or NeRF-synthetic, triangulated with its poses; used as SfM points are),
`random` (uniform in a ball of radius 0.5 in normalised units around the scene centre, i.e. half
the camera distance), or `auto` (mesh, else points, else triangulate, else random: the figure
`source` and the log line say which, as does `radfield info`). There are exactly
`train.max_primitives` of them when a budget is set (the paper's budget protocol starts from the
budget), else `init.num_points`: a point set is subsampled, or repeated with jitter.

Every primitive starts isotropic with identity rotation. A Gaussian's scale is d, the mean
distance to its 3 nearest neighbours (as 3DGS). A neural primitive gets the same spread: its
radius is k·d with k² the inverse per-axis variance of its density profile in the unit ball, so
its density has the Gaussian's variance d² along every axis: k = √7 for the window 1.5 (1 − r²)
(E[x²] = 1/7), √5 for a hard edge (uniform: E[x²] = 1/5). With radius d its density would spread
1/√7 as far as the Gaussian's (5 % of the volume), leaving gaps between neighbours that
densification must fill (docs/studies/seeds-radius-sh-viewsize.md:
k = 1 costs 0.1 to 0.7 dB val); `init.neural_radius` sets k by hand (0 = this automatic factor).
Random centres know nothing of the surfaces, and 2,000 of them spread over a scene lie far apart:
each is capped to cover RANDOM_FOOTPRINT_PX pixels in the training view where it looks largest
(`footprint_radius`; figure `footprint_px`), so that a random start is many small primitives too,
not a few that each cover most of a view (the volume samples beside a point source, below, keep
their spacing: they fill what lies between the points). A forward-facing capture's start is capped
the same way, at `init.footprint_px` (12): one whose training views' optical axes all lie within
`init.footprint_cone` (20°) of their mean direction (`axes_half_angle`), as LLFF's do. Seen from
nearly one direction, its sparse points' large primitives cover the same pixels in every view and
no view from the side carves them (fern at 504×378: axes within 10°; 14.6 M pixel–primitive pairs
a view, 1.0 M capped; its whole run 17 → 12–14 minutes and +0.28 dB held-out), where capping a
capture seen from around an object costs PSNR (fox_small, axes within 52°: −0.65 dB with every
primitive capped; lego_small: 92°; docs/studies/real-size.md).
The kind is `train.primitive`'s, or for a dynamic scene (views that carry a time) its
time-conditioned kind (`primitive_kind`: neural -> neural-dynamic, gaussian -> gaussian-dynamic;
kinds/dynamic.py), which starts as the static kind with zero temporal tensors, and for a
one-light-at-a-time capture (views that carry a light) its relightable kind (neural ->
neural-relight, gaussian -> gaussian-relight; kinds/relight.py), which starts as the static kind
with a colour network of zero output and SH degree 0 (the kind's init settings). D-NeRF datasets and
the dynamic demo scenes have no points: their centres are all sampled uniformly in the envelope,
the union of the moments' hulls (stages/envelope.py), or in the `random` ball without one.
SH DC from the point colour when known (the mesh's vertex colours, SfM or triangulated points' colours;
else 0.5 grey), higher bands zero. Neural primitives:
SIREN-style MLP weights (`siren_mlp_init`, paper §3.3) and b2 = −ln(1 − 0.1)/2 ≈ 0.0527: a ray
through the centre crosses τ-length 2 (the diameter in units of max(s)) and the cos terms average
out, so it sees opacity 1 − exp(−2 b2) = 0.1, the initial opacity of a 3DGS Gaussian. Gaussians:
opacity logit of 0.1, as 3DGS.

With an envelope (the envelope stage's envelope.ply), every centre starts inside it:
`init.cage_fraction` of them uniformly in its volume (uniform in its bounding box, kept when
inside: this covers what the points miss, such as textureless parts without SfM points), the rest
from the source, keeping only the points inside the envelope; anything the source cannot fill is
sampled in the volume too, as are all centres of the `random` source. Volume samples start grey.
An object dataset with alpha and no points (NeRF-synthetic) so starts from its triangulated points
inside its visual hull plus samples in the hull's volume.
The centres depend on the envelope and the seed only, never on the cage: fTetWild's cage differs
from run to run, and the same command must give the same model. `binding.npz` (radfield.core.geometry.cage)
then records every primitive's tet in the cage (the tetra stage's cage.npz) and the barycentric
coordinates of its centre, for the editor (a centre just outside the cage's surface, which
approximates the envelope's, extrapolates from the nearest tet); without a cage `tet` is -1
throughout.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree

from radfield.errors import RadfieldError
from radfield.model_file import save_model
from radfield.core import kinds
from radfield.core.splat.sh import num_sh_coeffs, rgb_to_sh_dc
from radfield.datasets.scene import POINTS, SCENE, Scene, load_scene
from radfield.pipeline.runner import Context, Stage
from radfield.core.geometry.cage import CAGE_NPZ, write_binding
from radfield.core.geometry.cameras import axes_half_angle
from radfield.core.geometry.envelope import inside_envelope, read_envelope, sample_in_envelope
from radfield import conditions
from radfield.stages.envelope import ENVELOPE
from radfield.stages.triangulate import TRIANGULATED

INIT_MODEL = "init.safetensors"  # the train stage's starting point (train writes model.safetensors)
BINDING = "binding.npz"  # the initial primitives' tets and barycentric coordinates in the cage
SOURCES = ("auto", "mesh", "points", "triangulate", "random")
# the arrays (centres, colours) each point source reads, in `auto`'s order: the data stage's points.npz,
# then the triangulate stage's points (run() adds them under these names)
POINT_SETS = {"mesh": ("mesh_vertices", "mesh_rgb"), "points": ("xyz", "rgb"),
              "triangulate": ("triangulated_xyz", "triangulated_rgb")}
SOURCE_WORDS = {"mesh": "the dataset's mesh.ply", "points": "SfM points", "triangulate": "triangulated points",
                "random": "random centres"}
RANDOM_RADIUS = 0.5  # normalised units: the cameras lie within radius 1
# A random start knows nothing of the surfaces: its primitives start this small, in pixels of the
# training view where each looks largest (their scale: a Gaussian's σ, a neural primitive's radius),
# and densification grows them where the images ask. Neighbour distances would size 2,000 centres
# spread over fern's scene to half its 504x378 view each (median radius 235 px: 137 M
# pixel-primitive pairs a view, 75 s a CPU step); fern's 1,872 triangulated points, which know
# where the surfaces are, start at a median 24 px.
RANDOM_FOOTPRINT_PX = 4


def run(ctx: Context) -> dict[str, Any]:
    cfg = ctx.config
    scene = load_scene(ctx.inputs[SCENE])
    with np.load(ctx.inputs[POINTS]) as points:
        point_sets = {name: points[name] for name in points.files}
    if ctx.inputs[TRIANGULATED] is not None:
        with np.load(ctx.inputs[TRIANGULATED]) as triangulated:
            point_sets |= dict(zip(POINT_SETS["triangulate"], (triangulated["xyz"], triangulated["rgb"])))
    budget = cfg["train"]["max_primitives"]
    count = cfg["init"]["num_points"] if budget is None else budget
    rng = np.random.default_rng(ctx.seed)
    cage_file, envelope_file = ctx.inputs[CAGE_NPZ], ctx.inputs[ENVELOPE]
    if envelope_file is None:
        source, means, rgb = initial_centres(scene, point_sets, cfg["init"]["source"], count, rng)
        in_volume = 0
    else:
        source, means, rgb, in_volume = centres_in_envelope(read_envelope(envelope_file), point_sets,
                                                            cfg["init"]["source"], count, cfg["init"]["cage_fraction"], rng)
    kind = primitive_kind(cfg, conditions.view_conditions(scene.splits))
    settings = kinds.get(kind).init_settings(cfg)
    radius, pixels, capped = footprint_cap(source, means, initial_radii(means, kind, scene.extent, settings),
                                           scene.cameras("train"), cfg["init"], scene.extent)
    prims = make_primitives(means, rgb, kind, cfg["train"]["sh_degree"], scene.extent, ctx.seed, settings,
                            radius=radius)
    save_model(ctx.outputs[INIT_MODEL], prims)
    write_binding(ctx.outputs[BINDING], means, cage_file)
    ctx.log(f"{len(prims)} {prims.kind} primitives from {SOURCE_WORDS[source]}"
            + ("" if not pixels else f" of at most {pixels:g} px ({capped} of them capped"
               + ("" if source == "random" else ": the views are forward-facing") + ")")
            + (f", {in_volume} of them sampled in the envelope's volume" if envelope_file is not None else ""))
    return {"primitives": len(prims), "params": prims.num_params(), "source": source,
            "cage_samples": in_volume, "bound": cage_file is not None,
            **({"footprint_px": pixels, "footprint_capped": capped} if pixels else {}),
            # a conditioned kind, chosen for views that carry a time or a light, is recorded (`radfield info`)
            **({"kind": prims.kind} if kinds.get(kind).conditions else {})}


STAGE = Stage(
    "init",
    run,
    # with the config keys every kind's init_settings reads (neural: render.omega0, hidden, window)
    config_keys=("init", "train.primitive", "train.sh_degree", "train.max_primitives",
                 *dict.fromkeys(key for kind in kinds.registered() for key in kind.init_config_keys), "seed"),
    inputs=(SCENE, POINTS, TRIANGULATED, ENVELOPE, CAGE_NPZ),
    outputs=(INIT_MODEL, BINDING),
    version=5,
)


def check_config(config: dict[str, Any], points: dict[str, np.ndarray], posed: bool = True) -> None:
    """The init settings a user can get wrong, checked before anything runs (`points`: the data
    stage's points.npz arrays; for unposed photos, whose points the sfm stage makes, only a
    mesh source can be missing; triangulated points are only known once the triangulate stage ran,
    but it serves posed datasets without points only). The kind against the views' conditions:
    `primitive_kind`."""
    source = config["init"]["source"]
    if source == "triangulate":
        if not posed or len(points["xyz"]) or len(points["mesh_vertices"]):
            own = "SfM points (from the sfm stage)" if not posed else "points or a mesh.ply"
            raise RadfieldError(f"config key init.source is triangulate but the dataset has its own {own}: "
                                f"triangulation is for posed datasets without any")
    elif posed or source == "mesh":
        choose_source(source, points)


def primitive_kind(config: dict[str, Any], carried: tuple[str, ...] | list[str]) -> str:
    """The kind the run trains (the one place train.primitive is read): train.primitive, or, when
    the views carry conditions (`carried`: conditions.view_conditions, after data.time and
    data.light drop the ignored ones), the registered kind that extends it with exactly those
    (time: neural -> neural-dynamic, gaussian -> gaussian-dynamic; light: neural -> neural-relight,
    gaussian -> gaussian-relight). A conditioned kind asked for on views that lack its condition is
    an error: it could not be drawn at any of them."""
    name = config["train"]["primitive"]
    kind = kinds.get(name)
    wanted = set(carried)
    missing = [c for c in kind.conditions if c not in wanted]
    if missing:
        ignored = config.get("data", {}).get(missing[0]) == "ignore"   # the init stage sees scene.json only
        why = f"data.{missing[0]} is ignore" if ignored else f"the dataset's views carry no {missing[0]}"
        words = conditions.get(missing[0]).kind_words
        raise RadfieldError(f"config key train.primitive is {name}, a {words} kind, but {why}: "
                            f"train a static kind (e.g. {static_kind(kind)})")
    return name if set(kind.conditions) == wanted else conditioned(kind, wanted).name


def conditioned(kind: kinds.PrimitiveKind, wanted: set[str]) -> kinds.PrimitiveKind:
    """The registered kind that extends `kind` (a subclass of its class) with the conditions `wanted`."""
    for other in kinds.registered():
        if set(other.conditions) == wanted and isinstance(other, type(kind)):
            return other
    ignore = " or ".join(f"data.{c}=ignore" for c in sorted(wanted))
    raise RadfieldError(f"primitive kind {kind.name} has no variant conditioned on {' and '.join(sorted(wanted))} "
                        f"for this dataset's views; set {ignore} to train it as if every view shared one")


def static_kind(kind: kinds.PrimitiveKind) -> str:
    """The registered static kind that `kind` extends (for the error's hint)."""
    return next((other.name for other in kinds.registered()
                 if not other.conditions and isinstance(kind, type(other))), "neural")


def choose_source(source: str, points: dict[str, np.ndarray]) -> str:
    """The point set `source` stands for ("auto" resolved); RadfieldError if the dataset lacks it."""
    if source not in SOURCES:
        raise RadfieldError(f"config key init.source must be one of {', '.join(SOURCES)}, got {source!r}")
    if source == "auto":
        return next((name for name, (xyz, _) in POINT_SETS.items() if len(points.get(xyz, ()))), "random")
    if source == "triangulate" and not len(points.get(POINT_SETS[source][0], ())):
        raise RadfieldError("config key init.source is triangulate but no points were triangulated "
                            "(see the triangulate stage)")
    if source != "random" and not len(points[POINT_SETS[source][0]]):
        what = "mesh.ply" if source == "mesh" else "SfM points"
        raise RadfieldError(f"config key init.source is {source} but the dataset has no {what}")
    return source


def initial_centres(scene: Scene, points: dict[str, np.ndarray], source: str, count: int,
                    rng: np.random.Generator) -> tuple[str, np.ndarray, np.ndarray | None]:
    """(source used, centres (count, 3), colours (count, 3) or None) in the world frame."""
    source = choose_source(source, points)
    if source == "random":
        radius = RANDOM_RADIUS / scene.normalization.scale
        direction = rng.normal(size=(count, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        r = radius * rng.random(count) ** (1 / 3)  # uniform in the ball's volume
        return source, scene.normalization.center.numpy() + direction * r[:, None], None
    xyz, rgb = (points[name] for name in POINT_SETS[source])
    xyz, rgb = xyz.astype(np.float64), rgb if len(rgb) == len(xyz) else None
    if source == "mesh" and len(points["mesh_faces"]):
        return source, *surface_samples(xyz, points["mesh_faces"], rgb, count, rng)
    return source, *resample(xyz, rgb, count, rng)


def centres_in_envelope(envelope: tuple[np.ndarray, np.ndarray], points: dict[str, np.ndarray], source: str,
                        count: int, volume_fraction: float,
                        rng: np.random.Generator) -> tuple[str, np.ndarray, np.ndarray | None, int]:
    """(source used, centres (count, 3) inside the envelope (vertices, faces), their colours or
    None, how many of them were sampled in the envelope's volume); see the module docstring."""
    source = choose_source(source, points)
    wanted = 0 if source == "random" else count - round(volume_fraction * count)
    means, rgb = np.zeros((0, 3)), None
    if wanted:
        xyz, rgb = (points[name] for name in POINT_SETS[source])
        xyz, rgb = xyz.astype(np.float64), rgb if len(rgb) == len(xyz) else None
        if source == "mesh" and len(points["mesh_faces"]):
            xyz, rgb = surface_samples(xyz, points["mesh_faces"], rgb, wanted, rng)
        else:
            xyz, rgb = _inside(envelope, xyz, rgb)
            if len(xyz):
                xyz, rgb = resample(xyz, rgb, wanted, rng)
        means, rgb = _inside(envelope, xyz, rgb)  # jittered copies and surface samples may lie just outside
    # the configured share of volume samples, plus whatever the source could not fill
    volume = sample_in_envelope(*envelope, count - len(means), rng)
    if rgb is not None:
        rgb = np.concatenate([rgb, np.full((len(volume), 3), 0.5)])
    return source, np.concatenate([means, volume]), rgb, len(volume)


def _inside(envelope: tuple[np.ndarray, np.ndarray], xyz: np.ndarray,
            rgb: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """The points (and their colours) that lie inside the envelope."""
    keep = inside_envelope(xyz, *envelope)
    return xyz[keep], None if rgb is None else rgb[keep]


def surface_samples(vertices: np.ndarray, faces: np.ndarray, rgb: np.ndarray | None, count: int,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray | None]:
    """`count` points spread uniformly over a triangle mesh's area, colours interpolated from the
    vertices: the paper resamples its meshes to each budget, and vertices crowd where a mesh is
    finely tessellated (a box's large faces have none inside)."""
    corners = vertices[faces]  # (F, 3 corners, 3)
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    face = rng.choice(len(faces), count, p=area / area.sum())
    root, v = np.sqrt(rng.random(count)), rng.random(count)
    weights = np.stack([1 - root, root * (1 - v), root * v], -1)  # uniform barycentric coordinates
    means = np.einsum("pc,pcx->px", weights, corners[face])
    return means, None if rgb is None else np.einsum("pc,pcx->px", weights, rgb[faces[face]])


def resample(xyz: np.ndarray, rgb: np.ndarray | None, count: int,
             rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray | None]:
    """`count` points from a point set: a random subset, or every point plus copies jittered by a
    fraction of the local spacing when the set is smaller (coincident centres would get zero scale)."""
    xyz, first = np.unique(xyz, axis=0, return_index=True)  # meshes repeat vertices along seams
    rgb = None if rgb is None else rgb[first]
    n = len(xyz)
    if n >= count:
        index = np.sort(rng.choice(n, count, replace=False))
        return xyz[index], None if rgb is None else rgb[index]
    index = np.concatenate([np.arange(n), rng.choice(n, count - n)])
    spacing = neighbour_distance(xyz)[index[n:]] if n > 1 else np.ones(count - n)
    means = xyz[index]
    means[n:] += rng.normal(size=(count - n, 3)) * 0.3 * spacing[:, None]
    return means, None if rgb is None else rgb[index]


def neighbour_distance(xyz: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean distance of every point to its k nearest other points."""
    k = min(k, len(xyz) - 1)
    distances, _ = cKDTree(xyz).query(xyz, k=k + 1)  # the nearest is the point itself
    return distances[:, 1:].mean(axis=1)


def footprint_radius(means: np.ndarray, cameras: list, pixels: float, chunk: int = 1 << 16) -> np.ndarray:
    """The radius (world units) at each centre that spans `pixels` pixels in the training view where
    it looks largest: `pixels` · z / f, z its depth and f the larger focal length of the camera that
    minimises z / f among those it lies in front of. Behind every camera (seen by no training view,
    but by a new one), z is the distance to the nearest camera's centre."""
    rows = np.stack([camera.w2c.double().numpy()[2] for camera in cameras])  # each camera's depth: row 3 of w2c
    centres = np.stack([camera.center.double().numpy() for camera in cameras])
    focal = np.array([max(camera.fx, camera.fy) for camera in cameras])
    out = np.empty(len(means))
    for start in range(0, len(means), chunk):   # (chunk, cameras) depths at a time: a budget of 1M centres
        part = means[start:start + chunk]
        depth = part @ rows[:, :3].T + rows[:, 3]
        seen = np.where(depth > 0, depth / focal, np.inf).min(axis=1)
        nearest = (np.linalg.norm(part[:, None] - centres[None], axis=-1) / focal).min(axis=1)
        out[start:start + chunk] = np.where(np.isfinite(seen), seen, nearest)
    return pixels * out


def footprint_cap(source: str, means: np.ndarray, radius: np.ndarray, cameras: list, init_cfg: dict,
                  extent: float) -> tuple[np.ndarray, float, int]:
    """The initial radii `radius` (world units, uncapped) capped where the start calls for it, the
    cap in pixels (0: none) and how many primitives it shrank. A random start: RANDOM_FOOTPRINT_PX.
    Any other: init.footprint_px when the training views are forward-facing (`axes_half_angle`
    under init.footprint_cone; 180: every capture); 0 in either turns it off."""
    if source == "random":
        pixels = RANDOM_FOOTPRINT_PX
    else:
        pixels, cone = init_cfg["footprint_px"], init_cfg["footprint_cone"]
        forward_facing = cone >= 180 or (cone > 0 and axes_half_angle(cameras) < cone)
        if pixels <= 0 or not forward_facing:
            return radius, 0.0, 0
    cap = footprint_radius(means, cameras, pixels)
    return np.maximum(np.minimum(radius, cap), 1e-6 * extent), pixels, int((radius > cap).sum())


def initial_radii(means: np.ndarray, kind: str, extent: float, settings: dict | None = None) -> np.ndarray:
    """Each primitive's initial radius before any cap (world units): the kind's multiple of the mean
    distance to the 3 nearest centres (see the module docstring)."""
    radius = neighbour_distance(means) if len(means) > 1 else np.full(1, 0.01 * extent)
    return kinds.get(kind).initial_radius(np.maximum(radius, 1e-6 * extent), settings or {})


def make_primitives(means: np.ndarray, rgb: np.ndarray | None, kind: str, sh_degree: int, extent: float,
                    seed: int, settings: dict | None = None, radius: np.ndarray | None = None) -> kinds.Primitives:
    """Isotropic primitives of `kind` at `means` (see the module docstring for every initial value);
    `settings`: the kind's init settings (kinds.get(kind).init_settings(config); None: its defaults,
    neural: ω0 30, 8 hidden units, hard-edged, W1 bound 1/3, the automatic radius factor); their
    "sh_degree", when the kind sets one, wins over `sh_degree` (the relightable kinds: 0, eq. 14).
    `radius` (per primitive, world units): the initial radii, when not `initial_radii`'s (the init
    stage's are capped: `footprint_cap`)."""
    spec, settings = kinds.get(kind), settings or {}
    num = len(means)
    radius = initial_radii(means, kind, extent, settings) if radius is None else radius
    colour = torch.full((num, 3), 0.5) if rgb is None else torch.as_tensor(rgb, dtype=torch.float32)
    sh = torch.zeros(num, num_sh_coeffs(settings.get("sh_degree", sh_degree)), 3)
    sh[:, 0] = rgb_to_sh_dc(colour)
    geometry = {
        "means": torch.as_tensor(means, dtype=torch.float32),
        "log_scales": torch.log(torch.as_tensor(radius, dtype=torch.float32))[:, None].repeat(1, 3),
        "quats": torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(num, 1),
        "sh": sh,
    }
    return spec.from_points(geometry, settings, seed)
