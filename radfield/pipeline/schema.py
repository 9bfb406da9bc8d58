"""The pipeline configuration's schema: one dataclass per section of `pipeline.yaml`, with a type
and a docstring per key (as nerfstudio's and gsplat's configs).

`pipeline.yaml` stays the file of defaults: every key's default is there and only there. These
classes say the rest, each fact once:

- a key's type is its annotation: `int`, `float` (an integer is taken too), `bool`, `str`;
  `int | None` may be null; `Literal["a", "b"]` is one of these values; `tuple[float, float, float]`
  is a list of 3 numbers, `tuple[str, ...]` a list of any length;
- its range (numbers: `radfield.util.ranges.Range`), choices known only once a registry is
  imported, the command-line flag that sets it, and whether it selects from its default's items
  are `setting(...)` metadata;
- what it is, its units and its effect are the string under the field.

pipeline/config.py checks `--config`, `--set` and the CLI's flags against these classes (and that
`pipeline.yaml` names the same keys, in the same order, with defaults that fit);
pipeline/reference.py writes docs/configuration.md from them.

A resolved config (load_config's result) is a plain nested dict: RUN/config.yaml, the stages' parts
of it and their cache keys are dicts. `typed(config)` is the same config as a `Config`
(`typed(config).train.lr.means`), and `plain(...)` the way back.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar, Union

from radfield.util.ranges import AT_LEAST_0, AT_LEAST_1, FRACTION, POSITIVE, Range


def _primitive_kinds() -> tuple[str, ...]:
    """The registered primitive kinds (radfield.core.kinds, imported when a value is checked: it needs torch)."""
    from radfield.core import kinds

    return kinds.names()


def setting(range: Range | None = None, *, choices: Callable[[], tuple[str, ...]] | None = None,
            flag: str | None = None, selection: bool = False) -> Any:
    """A key's facts besides its type: the `range` of a number (of each item of a list); `choices`,
    the values it takes when only a registry knows them (read when a value is checked); the `flag`
    that sets it on every command (its error lines name the flag the user typed, not the key);
    `selection`: a list of any of its default's items, in any order (the stage list)."""
    return field(metadata={"range": range, "choices": choices, "flag": flag, "selection": selection})


S = TypeVar("S", bound="Section")


class Section:
    """A section of the config (a dataclass): made from its part of a resolved config, and back."""

    @classmethod
    def from_dict(cls: type[S], data: Mapping[str, Any]) -> S:
        """The section from its nested dict, which must hold exactly its keys (a resolved, checked config's)."""
        names = [f.name for f in dataclasses.fields(cls)]
        if set(data) != set(names):
            raise ValueError(f"{cls.__name__}: {sorted(set(data) ^ set(names))} differ from the schema's keys")
        hints = _hints(cls)
        return cls(**{name: hints[name].from_dict(value) if _is_section(hints[name])
                      else tuple(value) if isinstance(value, list) else value
                      for name, value in data.items()})

    def to_dict(self) -> dict[str, Any]:
        """The section as a resolved config holds it: nested dicts, lists for tuples."""
        return {f.name: plain(getattr(self, f.name)) for f in dataclasses.fields(self)}


# --- the sections of pipeline.yaml, in its order ------------------------------------------------

@dataclass(frozen=True)
class DataConfig(Section):
    """`data`: how the dataset's images are read and split."""

    downscale: int | None = setting(AT_LEAST_1, flag="--downscale")
    """Integer factor every image is downscaled by on load (1: full size). null: automatic, 1 or the
    smallest factor that brings the largest image within data.max_size (one note line says so); a run
    records the factor it resolved (RUN/config.yaml, scene.json), and every later command uses it."""
    max_size: int = setting(Range(0, note="pixels, 0 = no limit"))
    """With an automatic data.downscale (null): the longest image side, in pixels, that training
    takes without downscaling (nerfstudio's 1600); an explicit data.downscale (--downscale) wins."""
    background: tuple[float, float, float] = setting(FRACTION, flag="--background")
    """RGB in [0, 1] that RGBA images are composited on, and that every render is drawn over."""
    test_every: int = setting(Range(2))
    """Hold out every N-th image as a test view, when the dataset has no split of its own."""
    val_every: int = setting(Range(0, note="0 = no val split"))
    """> 0: every N-th training view becomes a validation view (split "val", not trained on; for tuning
    and selection: eval.split=val). 0: no val split, unless the dataset has one."""
    time: Literal["auto", "ignore"]
    """A dynamic dataset (frames with a "time", D-NeRF): auto trains the time-conditioned kind of
    train.primitive (neural -> neural-dynamic, gaussian -> gaussian-dynamic); ignore drops the views'
    times and trains the static kind as if every frame showed one moment (a baseline)."""
    light: Literal["auto", "ignore"]
    """A one-light-at-a-time capture (frames with a light_position or light_direction): auto trains the
    relightable kind of train.primitive (neural -> neural-relight, gaussian -> gaussian-relight); ignore
    drops the views' lights and trains the static kind, blind to the light (a baseline)."""


@dataclass(frozen=True)
class SfmConfig(Section):
    """`sfm`: posing a folder of photos with COLMAP (pycolmap); also the triangulate stage's features and
    matching (points for a posed dataset without any)."""

    num_threads: int = setting(Range(1, also=-1, note="-1 = all cores"))
    """CPU threads for COLMAP (-1: all cores). 1 keeps SfM deterministic: the same command gives the same model."""
    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV",
                          "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE"]
    """COLMAP camera model fitted before undistortion to a pinhole camera (one shared camera when all
    photos have the same size); the choices are COLMAP's models that undistort to a pinhole."""
    max_image_size: int = setting(AT_LEAST_1)
    """Longest image side used for feature extraction, in pixels."""
    max_num_features: int = setting(AT_LEAST_1)
    """SIFT features per image."""
    exhaustive_max_images: int = setting(AT_LEAST_1)
    """Exhaustive matching up to this many images, sequential matching above."""
    sequential_overlap: int = setting(AT_LEAST_1)
    """Neighbours (in file-name order) each image is matched with in sequential mode."""
    min_registered_fraction: float = setting(Range(0, 1, open_low=True))
    """Fail unless at least this fraction of the images registers."""
    target_radius: float = setting(POSITIVE)
    """Camera centres fit in a sphere of this radius after normalisation."""


@dataclass(frozen=True)
class EnvelopeConfig(Section):
    """`envelope`: the closed coarse surface around the object that the cage fills."""

    source: Literal["auto", "points", "mesh", "hull", "triangulate", "none"]
    """What the envelope is built from: points (SfM), mesh (the dataset's mesh.ply), hull (visual hull of
    the alpha masks), triangulate (the triangulate stage's points: features of the posed images), auto
    (the first of these the dataset has), none (no envelope, no cage: envelope and tetra are not
    applicable, as with `reconstruct --no-cage`)."""
    method: Literal["auto", "poisson", "ball_pivoting", "alpha", "convex"]
    """Surface through the points (auto = poisson). The alpha shape, then the convex hull, are the
    fallbacks when it is open or misses points; every branch ends in the convex hull, then the box, of
    what it must hold (figures `fallback`, `fallback_reason`, and one warning line)."""
    outlier_std: float = setting(POSITIVE)
    """Drop points whose neighbour spacing exceeds the mean by this many standard deviations."""
    poisson_depth: int = setting(Range(1, 16))
    """Octree depth of the screened Poisson reconstruction (6: coarse on purpose)."""
    wrap_alpha: float = setting(POSITIVE)
    """Smallest feature the envelope follows, as a fraction of the bounding-box diagonal."""
    offset: float = setting(POSITIVE)
    """Outward margin, as a fraction of the bounding-box diagonal."""
    target_faces: int = setting(Range(20))
    """Envelope faces after decimation (closed decimation: fast-simplification, else topology-preserving
    quadric collapse, else a coarser wrap)."""
    hull_resolution: int = setting(Range(8))
    """Visual hull: voxels along the longest side of the object's box."""
    num_threads: int = setting(AT_LEAST_1)
    """Poisson threads (OpenMP spin-waits make 2 far slower on a busy 2-core machine)."""


@dataclass(frozen=True)
class TetraConfig(Section):
    """`tetra`: the editing cage, a coarse tet mesh of the envelope (fTetWild)."""

    edge_length_fac: float = setting(Range(0, 1, open_low=True, open_high=True))
    """fTetWild's ideal edge length, as a fraction of the envelope's bounding-box diagonal."""
    epsilon: float = setting(Range(0, 1, open_low=True, open_high=True))
    """How far the cage surface may stray from the envelope, as a fraction of the diagonal."""
    coarsen: bool
    """Let fTetWild merge tets as far as quality allows (a coarse cage is the point)."""
    optimize: bool
    """fTetWild's mesh quality optimisation (slower, better tets)."""
    num_threads: int = setting(AT_LEAST_1)
    """fTetWild threads. Its cage differs run to run even so: nothing training uses depends on it. When
    fTetWild fails, a Delaunay cage of the envelope is the fallback."""


@dataclass(frozen=True)
class InitConfig(Section):
    """`init`: the starting primitives."""

    num_points: int = setting(AT_LEAST_1)
    """Primitives to start with."""
    source: Literal["auto", "mesh", "points", "triangulate", "random"]
    """Where the initial centres come from: mesh (surface of the dataset's mesh.ply), points (SfM
    points), triangulate (the triangulate stage's points: a posed dataset without any), random (in the
    scene bounds, or in the envelope; each sized to cover a few pixels of the training views), auto
    (mesh, else points, else triangulate, else random)."""
    w1_scale: float = setting(Range(0, 10))
    """Neural: W1 ~ U(−w1_scale, w1_scale) at the start (the paper's SIREN init: 1/3), the initial
    frequency scale of the density MLP (frequencies ω0 · W1 per unit of u = (x − μ)/max(s))."""
    neural_radius: float = setting(Range(0, 10, note="0 = automatic"))
    """Neural: initial radius k·d, d the mean distance to the 3 nearest centres (a Gaussian's: its
    spread). 0: automatic, k = √7 with the density window, √5 without
    (docs/studies/seeds-radius-sh-viewsize.md)."""
    footprint_px: float = setting(Range(0, 1000, note="pixels, 0 = off"))
    """A forward-facing capture's start (init.footprint_cone): every initial radius at most this many
    pixels in the training view where the primitive looks largest, so that its sparse points start
    as small primitives, not large ones that each cover much of every view (a random start is always
    capped at 4 px). 0: off. Fern at 504×378: 17 → 12–14 minutes and +0.28 dB
    (docs/studies/real-size.md)."""
    footprint_cone: float = setting(Range(0, 180, note="degrees, 0 = off, 180 = every capture"))
    """init.footprint_px caps the start when every training view's optical axis lies within a cone of
    this half-angle about their mean direction (forward-facing, as LLFF's captures). 20: fern (axes
    within 10°), not fox_small (52°) or lego_small (92°); capping fox_small's start costs 0.65 dB
    (docs/studies/real-size.md)."""
    cage_fraction: float = setting(FRACTION)
    """With an envelope: this fraction starts uniformly in its volume, the rest from the source inside
    it (the envelope, not fTetWild's cage, so that the same command gives the same model)."""


@dataclass(frozen=True)
class LearningRates(Section):
    """`train.lr`: Adam learning rates per parameter group (0 freezes a group)."""

    means: float = setting(Range(0, note="0 freezes the group"))
    """Centres, × the scene extent (decays to means_lr_final_ratio of it by the last step)."""
    log_scales: float = setting(Range(0, note="0 freezes the group"))
    """Log-scales of the ellipsoids' axes."""
    quats: float = setting(Range(0, note="0 freezes the group"))
    """Rotation quaternions."""
    sh_dc: float = setting(Range(0, note="0 freezes the group"))
    """The colour's degree-0 spherical-harmonics coefficients."""
    sh_rest: float = setting(Range(0, note="0 freezes the group"))
    """The higher spherical-harmonics coefficients (sh_dc / 20)."""
    mlp: float = setting(Range(0, note="0 freezes the group"))
    """Neural: the density MLP's weights w1, b1, w2, b2."""
    color: float = setting(Range(0, note="0 freezes the group"))
    """Relightable kinds: the colour network (3× mlp: on olat 27.54 dB against 27.20 at 1×; docs/usage.md
    "Relighting")."""
    opacities: float = setting(Range(0, note="0 freezes the group"))
    """Gaussian primitives only: opacities."""


@dataclass(frozen=True)
class GaussianDensify(Section):
    """`train.densify.gaussian`: the standard 3DGS recipe, for --primitive gaussian (it replaces
    grad_threshold, prune_threshold and prune_scale)."""

    grad_threshold: float = setting(AT_LEAST_0)
    """Clone or split Gaussians whose mean screen-space (NDC) gradient exceeds this."""
    min_opacity: float = setting(Range(0, 1, open_high=True))
    """Prune Gaussians more transparent than this."""
    prune_scale: float = setting(POSITIVE)
    """After the first opacity reset, prune Gaussians larger than this fraction of the scene extent."""
    opacity_reset_every: int = setting(AT_LEAST_1)
    """Clamp every opacity to at most 0.01 every this many steps (1000 keeps two resets inside the
    densification window)."""


@dataclass(frozen=True)
class Densify(Section):
    """`train.densify`: population control (clone, split, prune) of the neural primitives."""

    start: int = setting(AT_LEAST_0)
    """Densify from this step on."""
    stop: int = setting(AT_LEAST_0)
    """... until this step (gradient statistics are gathered until then)."""
    every: int = setting(AT_LEAST_1)
    """Densify and prune at the steps that are multiples of this."""
    grad_threshold: float = setting(AT_LEAST_0)
    """Clone or split primitives whose mean MLP-weight gradient norm exceeds this, for 64×64 views;
    scaled by √(4096 / pixels per view), as the signal falls as 1/√pixels
    (docs/studies/seeds-radius-sh-viewsize.md)."""
    prune_threshold: float = setting(AT_LEAST_0)
    """Prune visible primitives whose mean MLP-weight gradient norm stays below this (scaled alike)."""
    grow_scale: float = setting(POSITIVE)
    """Clone below this scale (fraction of the scene extent), split above."""
    prune_scale: float = setting(POSITIVE)
    """Prune primitives larger than this fraction of the scene extent (the cameras' radius;
    docs/studies/density-window.md)."""
    gaussian: GaussianDensify


@dataclass(frozen=True)
class TrainConfig(Section):
    """`train`: the optimisation."""

    primitive: str = setting(choices=_primitive_kinds, flag="--primitive")
    """The kind of primitive: neural (splattable neural primitives), gaussian (the 3DGS baseline); the
    time-conditioned (…-dynamic) and relightable (…-relight) kinds are chosen by themselves on a dynamic
    or one-light-at-a-time dataset (data.time, data.light)."""
    iterations: int = setting(AT_LEAST_1, flag="--iterations")
    """Optimisation steps. Raising it on a finished run continues from its final state
    (RUN/train/final_state.safetensors): Adam moments and the population are kept, and the schedules
    become those of a run of the new length at the reached step."""
    max_primitives: int | None = setting(AT_LEAST_1, flag="--max-primitives")
    """Hard primitive budget (the paper's memory-budget protocol); null: unbounded."""
    sh_degree: int = setting(Range(0, 3))
    """Final spherical-harmonics degree of the colour (the relightable kinds train 0 whatever this says:
    eq. 14's constant colour)."""
    sh_increase_every: int = setting(AT_LEAST_1)
    """Raise the active SH degree by one every this many steps."""
    lambda_dssim: float = setting(FRACTION)
    """λ of the loss (1 − λ) L1 + λ D-SSIM."""
    lambda_aniso: float = setting(AT_LEAST_0)
    """Weight of the anisotropy regulariser std(s)/min(s)."""
    lambda_w1: float = setting(Range(0, note="0 = off"))
    """Neural: weight of the frequency penalty mean ‖W1‖²_F (smooth densities)."""
    lambda_density: float = setting(Range(0, note="0 = off"))
    """Neural: weight of the density penalty mean (‖W2‖₁ + |b2|) (an L1 opacity term)."""
    frequency_cap: float = setting(Range(0, note="0 = no cap"))
    """Neural: c of the anti-aliasing bound ω0‖W1_n‖ ≤ c · ρ_max on every hidden unit's frequency (rad per
    unit of u), ρ_max the primitive's largest projected radius in pixels over the training views (π: 2
    pixels per period, Nyquist; docs/studies/frequency-cap.md)."""
    frequency_bound: float = setting(Range(0, note="0 = no bound"))
    """Neural: K of the absolute bound ω0‖W1_n‖ ≤ K (rad per unit of u = (x − μ)/max(s), whatever the
    footprint; π: at most half a period over the radius; docs/studies/few-view-captures.md)."""
    nonnegative_density: float = setting(Range(0, 180, note="degrees, 0 = off"))
    """Neural: θ in degrees. After every step, the primitives whose training views lie within a cone of
    half-angle < θ about their mean direction get (W2, b2) projected onto ‖W2‖₁ ≤ b2, so that their
    density is ≥ 0 everywhere (paper eq. 6's bound); 180: every primitive
    (docs/studies/few-view-captures.md)."""
    ray_jitter: float = setting(Range(0, 1, note="pixels, 0 = off"))
    """Anti-aliasing: render each training view with its principal point moved by a random offset
    uniform in [-a/2, a/2]² pixels (a = this), so that training fits the pixels' area averages
    (docs/studies/edges-supersampling.md: render.supersample is the remedy that works)."""
    min_footprint: float = setting(Range(0, 8, note="pixels, 0 = off"))
    """Anti-aliasing: after every step raise each scale axis to at least this many pixels of the
    primitive's finest training view, s_i ≥ k·z/f (Mip-Splatting's 3D filter bound)."""
    random_background: bool
    """RGBA views: composite each training view on a random colour every step (and render over it), so
    that transparent pixels constrain density, not colour; no effect on photos without alpha."""
    coarse_levels: int = setting(Range(0, 4, note="0 = full size throughout"))
    """Coarse to fine: the early steps train on views downscaled 2^L times (area averages), the size
    doubling L times at equal intervals up to full size at coarse_until × iterations
    (core/train/coarse_to_fine.py, after DashGaussian's resolution schedule)."""
    coarse_until: float = setting(Range(0, 1, open_low=True))
    """The fraction of the iterations by which coarse to fine reaches full size."""
    lr: LearningRates
    means_lr_final_ratio: float = setting(Range(0, 1, open_low=True))
    """The means' rate decays exponentially to this fraction by the last step."""
    densify: Densify
    checkpoint_every: int = setting(AT_LEAST_1)
    """Steps between checkpoints (a killed run resumes from the last one)."""
    batch_views: int = setting(AT_LEAST_1)
    """Training views per step (of the whole job: split across the ranks of a distributed run)."""
    eval_every: int = setting(Range(0, note="0 = never"))
    """Log the held-out (test) views' PSNR every this many steps and at the last step
    (RUN/train/log.jsonl, curves.png); for information only, it never picks a model."""
    log_every: int | None = setting(Range(1, note="null: 1 on the CPU, 50 on a GPU"))
    """Read the steps' loss and PSNR off the device every this many steps (and at refinement, held-out,
    checkpoint and last steps) for the log and the progress bar; the log is the same whatever this is.
    null: 1 on the CPU, 50 on a GPU (each read waits for the GPU's queue)."""


@dataclass(frozen=True)
class DistributedConfig(Section):
    """`distributed`: data-parallel training under torchrun or --nproc (docs/usage.md "Distributed
    training"); not part of any cache key (the model does not depend on it)."""

    timeout: float = setting(POSITIVE)
    """Seconds a training collective waits for the other ranks (also while rank 0 alone measures the
    held-out views or writes a checkpoint) before the job fails."""
    sync_check_every: int = setting(Range(0, note="0 = only at the start"))
    """Compare a checksum of the parameters across the ranks every this many steps; a difference is an
    error naming the ranks and the step."""


@dataclass(frozen=True)
class RenderConfig(Section):
    """`render`: how primitives are drawn, in training and every later render."""

    near: float = setting(POSITIVE, flag="--near")
    """Near plane distance."""
    omega0: float = setting(POSITIVE)
    """ω0, the frequency of the density MLP's cosine (paper eq. 5; the paper's 30 overfits small views,
    docs/studies/quality-omega0.md)."""
    hidden: int = setting(Range(1, 64))
    """N, hidden units of the density MLP."""
    window: bool
    """Neural: the density is σ(x) · 1.5 (1 − r²), r the ellipsoid radius of x, so that it falls to 0 on
    the ellipsoid and a primitive's silhouette is smooth; false: the paper's hard-edged ellipsoid.
    Recorded in the model file (metadata `window`)."""
    supersample: int = setting(Range(1, 4, note="1 = off"))
    """Anti-aliasing: every pixel is the mean of n × n rays through its sub-pixel centres (n = this), in
    training and every later render, at n² the cost. Recorded in the model file (metadata `supersample`);
    ply-3dgs/splat export warns (one ray a pixel). docs/studies/edges-supersampling.md."""
    time_frequency: float = setting(Range(0, 100, open_low=True, note="1: the paper's ω; 2π: one period"))
    """Dynamic kinds: ω of the temporal colour's Fourier terms cos/sin(i ω ξ) (paper eq. 11-12: 1, less
    than one period over ξ in [0, 1]). Recorded in the model file."""


@dataclass(frozen=True)
class EvalConfig(Section):
    """`eval`: the measurement of the trained model."""

    split: Literal["train", "val", "test"]
    """The split the eval and bake stages measure."""


@dataclass(frozen=True)
class BakeConfig(Section):
    """`bake`: the delivery model (RUN/bake/baked.safetensors)."""

    min_weight: float = setting(Range(0, 1, open_high=True), flag="--min-weight")
    """Prune primitives whose transmittance-weighted alpha stays below this (1/255) at every pixel of
    every training view (tested through its upper bound, the per-view sum)."""
    fp16: bool
    """Store the baked tensors as float16 (half the size)."""


@dataclass(frozen=True)
class Config(Section):
    """The whole pipeline configuration (`pipeline.yaml`, RUN/config.yaml)."""

    stages: tuple[str, ...] = setting(selection=True)
    """The stages to run, in order: any of pipeline.yaml's, each once (sfm poses a folder of photos;
    triangulate finds points for a posed dataset without any; envelope and tetra build the editing cage; bind binds the trained model to it; bake writes the
    pruned delivery model; eval measures the trained model)."""
    seed: int = setting(AT_LEAST_0, flag="--seed")
    """Random seed of every stage that draws random numbers."""
    device: str = setting(flag="--device")
    """Torch device: cpu, cuda, cuda:1, ... (not part of any stage's cache key)."""
    data: DataConfig
    sfm: SfmConfig
    envelope: EnvelopeConfig
    tetra: TetraConfig
    init: InitConfig
    train: TrainConfig
    distributed: DistributedConfig
    render: RenderConfig
    eval: EvalConfig
    bake: BakeConfig


# --- reading the schema ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Key:
    """One key (a leaf) of the schema, as validation reads it."""

    name: str                 # dotted: "train.lr.means"
    type: type                # bool, int, float or str: the value's, or each list item's
    nullable: bool            # may be null (`int | None`)
    length: int | None        # a list: its length (None: any); not a list: None (see `is_list`)
    is_list: bool
    choices: tuple[str, ...] | Callable[[], tuple[str, ...]] | None   # Literal's values, or setting(choices=)
    range: Range | None
    flag: str | None
    selection: bool


def typed(config: Mapping[str, Any]) -> Config:
    """A resolved config (load_config's or run_config's result) as a `Config`."""
    return Config.from_dict(config)


def plain(value: Any) -> Any:
    """A config value as a resolved config holds it (a fresh copy): sections as dicts, tuples as lists."""
    if isinstance(value, Section):
        return value.to_dict()
    if isinstance(value, Mapping):
        return {name: plain(item) for name, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(item) for item in value]
    return value


def find(name: str) -> Key | type[Section] | None:
    """The key or the section class that a dotted name names ("train.lr.means", "train.lr"), or None."""
    return _names().get(name)


def names() -> list[str]:
    """Every dotted name of the schema, sections and keys, in order ("stages", ..., "data", "data.downscale", ...)."""
    return list(_names())


def keys() -> dict[str, Key]:
    """Every key (leaf) of the schema by dotted name, in order."""
    return {name: entry for name, entry in _names().items() if isinstance(entry, Key)}


@functools.cache
def docs(cls: type[Section]) -> dict[str, str]:
    """The docstring under each field of a section class (read from the source, as nerfstudio's tyro
    does: Python keeps no attribute docstrings), whitespace folded to single spaces."""
    body = ast.parse(inspect.getsource(cls)).body[0].body
    out = {}
    for node, after in zip(body, body[1:]):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and \
                isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant):
            out[node.target.id] = " ".join(str(after.value.value).split())
    return out


@functools.cache
def _names() -> dict[str, Key | type[Section]]:
    out: dict[str, Key | type[Section]] = {}

    def walk(cls: type[Section], prefix: str) -> None:
        hints = _hints(cls)
        for spec in dataclasses.fields(cls):
            name, hint = f"{prefix}{spec.name}", hints[spec.name]
            if _is_section(hint):
                out[name] = hint
                walk(hint, f"{name}.")
            else:
                out[name] = _key(name, hint, spec)

    walk(Config, "")
    return out


@functools.cache
def _hints(cls: type[Section]) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _key(name: str, hint: Any, spec: dataclasses.Field) -> Key:
    nullable = typing.get_origin(hint) in (Union, types.UnionType) and type(None) in typing.get_args(hint)
    if nullable:
        (hint,) = [arg for arg in typing.get_args(hint) if arg is not type(None)]
    is_list, length = typing.get_origin(hint) is tuple, None
    if is_list:
        items = typing.get_args(hint)
        hint, length = items[0], None if items[-1] is Ellipsis else len(items)
    choices = spec.metadata.get("choices")
    if typing.get_origin(hint) is Literal:
        choices, hint = typing.get_args(hint), str
    return Key(name, hint, nullable, length, is_list, choices, spec.metadata.get("range"),
               spec.metadata.get("flag"), spec.metadata.get("selection", False))


def _is_section(hint: Any) -> bool:
    return isinstance(hint, type) and issubclass(hint, Section)
