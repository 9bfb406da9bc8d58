"""What every primitive kind shares, and the registry of kinds.

A primitive kind is one `PrimitiveKind` object, registered once (`register`), that says for its
primitives everything the rest of radfield asks about them:

- the container: a dataclass of `Primitives` (the shared ellipsoid geometry μ, log s, q and the
  SH colour, plus the kind's own tensors) and the non-tensor `attributes` it carries (e.g. ω0);
- its parameters: `own_params` (name -> shape after P, in trained order), the train.lr key of each
  (`lr_keys`), the tensors a model file may omit (`optional`), metadata written and validated
  (`write_metadata`, `read_metadata`);
- rendering: the torch twin's per-view preparation (`twin_view`: pixel bounds, visibility and the
  per-primitive view tensors) and pair kernel (`pair_kernel`); a fused or GPU backend's whole-view
  implementation is registered with radfield.core.backends (op "view.<kind>") by the kind's module;
  the slow reference's per-pixel α (`reference_alpha`, core/render/reference.py);
- training: population control (`strategy`), extra loss terms (`regularisers`), projections after
  every optimiser step (`training_rules`), and how it starts from points (`initial_radius`,
  `from_points`, `init_settings`);
- editing and delivery: what a per-primitive affine map, a similarity or a halving does to its own
  tensors (`deformed`, `rotated`, `halved`; the geometry and SH are mapped by edit/affine.py and
  edit/compose.py for every kind), whether two models of the kind combine (`check_combinable`,
  `harmonise`), its peak density (`peak_density`), its 3D Gaussians (`to_gaussians`), and
  capability flags (`retrainable_locally`, `exact_gaussians`);
- the benchmark models it contributes (`bench_variants`, `bench_models`).

The defaults below are those of a kind that has only the shared geometry and its own opacity-like
tensors: no metadata, no regulariser, no per-step projection, a fixed population, nothing to map
under an edit besides the geometry. A kind's own tensors must not change under the similarity that
normalises a scene for training (stages/train.py moves only μ and log s): densities are measured
in units of the primitive's size, as the built-in kinds' are. Nothing outside a kind's module
branches on the kind: code asks `of(prims)` or `get(name)`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any, Callable, NamedTuple

import torch

from radfield.core.splat.sh import sh_degree_from_coeffs
from radfield.errors import RadfieldError
from radfield.util.registry import Registry

if TYPE_CHECKING:
    from radfield.core.geometry.cameras import Camera
    from radfield.core.splat.view import ViewFrame

# the geometry every kind has, as the file stores it (SH last: a kind's own tensors go in between)
GEOMETRY = {"means": (3,), "log_scales": (3,), "quats": (4,)}
SH = {"sh": ("K", 3)}
# the geometry as training holds it: SH split into its DC band and the rest (they learn at different rates)
TRAIN_GEOMETRY = ("means", "log_scales", "quats", "sh_dc", "sh_rest")
INITIAL_ALPHA = 0.1  # a new primitive's opacity through its centre, 3DGS's initial opacity (stages/init.py)


@dataclass
class Primitives:
    """Any kind's primitives: the shared geometry and SH that every kind's dataclass extends."""

    means: torch.Tensor       # (P, 3) centres μ
    log_scales: torch.Tensor  # (P, 3) ℓ, scales s = exp(ℓ)
    quats: torch.Tensor       # (P, 4) rotation q, w x y z, need not be normalised
    sh: torch.Tensor          # (P, K, 3) SH coefficients, K = (degree+1)^2
    # rays per pixel side the model was trained with (render.supersample, core/render/antialias.py): every
    # render for a user draws each pixel as the mean of n × n rays; the model file's `supersample`
    # key (absent = 1). Keyword-only, so it follows the subclasses' fields; map/to/select keep it.
    supersample: int = field(default=1, kw_only=True)

    kind = "base"

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_coeffs(self.sh.shape[1])

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    def tensors(self) -> dict[str, torch.Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self) if isinstance(getattr(self, f.name), torch.Tensor)}

    def num_params(self) -> int:
        return sum(t.numel() for t in self.tensors().values())

    def map(self, fn) -> "Primitives":
        """A copy with `fn` applied to every tensor (e.g. `lambda t: t.to(device)`)."""
        return replace(self, **{k: fn(v) for k, v in self.tensors().items()})

    def to(self, device=None, dtype=None) -> "Primitives":
        return self.map(lambda t: t.to(device=device, dtype=dtype))

    def select(self, index) -> "Primitives":
        return self.map(lambda t: t[index])


class PixelRay(NamedTuple):
    """One pixel's ray for the slow reference renderer (core/render/reference.py), float64: the
    camera, the image point (u, v), the ray's origin and unit direction in the world, the near
    plane and its distance along this ray."""

    camera: "Camera"
    u: float
    v: float
    origin: torch.Tensor
    direction: torch.Tensor
    near: float
    l_near: float


class PrimitiveKind:
    """One primitive kind (module docstring). Subclasses set the class attributes and override the
    hooks their primitives need; `register(kind_object)` makes it known."""

    name: str = "base"
    primitives: type = Primitives
    own_params: dict[str, tuple] = {}          # trained tensors besides the geometry, name -> shape after P
    lr_keys: dict[str, str] = {}               # parameter -> its train.lr key, where not its own name
    optional: dict[str, tuple] = {}            # tensors a model file may hold or not, name -> shape after P
    attributes: tuple[str, ...] = ()           # non-tensor fields training and model files carry
    retrainable_locally: bool = False          # edit/retrain.py can refit a region: one density σ(x), an SH colour
    exact_gaussians: bool = False              # its primitives are 3D Gaussians (exported as they are)
    support_radius: float = 1.0                # its extent in units of its scales: the ellipsoid (Gaussians: 3σ)
    bench_variants: tuple[str, ...] = ()       # the rows it adds to bench-render / bench-train
    # what a view must carry for the kind to be drawn, by condition name (radfield/conditions; "time":
    # Camera.conditions["time"], the moment ξ_t in [0, 1] of a time-conditioned kind, kinds/dynamic.py);
    # commands ask it before rendering or exporting
    conditions: tuple[str, ...] = ()

    # --- parameters ----------------------------------------------------------------------------

    def param_names(self) -> tuple[str, ...]:
        """The trained tensors in optimiser order (SH split into sh_dc and sh_rest)."""
        return TRAIN_GEOMETRY + tuple(self.own_params)

    def lr_key(self, param: str) -> str:
        return self.lr_keys.get(param, param)

    def attrs(self, prims) -> dict[str, Any]:
        """The kind's non-tensor attributes of `prims` (JSON values: checkpoints carry them)."""
        return {name: getattr(prims, name) for name in self.attributes}

    def default_attrs(self) -> dict[str, Any]:
        """The attributes' defaults (the dataclass's), for a checkpoint that lacks one."""
        defaults = {f.name: f.default for f in fields(self.primitives)}
        return {name: defaults[name] for name in self.attributes}

    def assemble(self, tensors: dict[str, torch.Tensor], attrs: dict[str, Any] | None = None, **extra):
        """Primitives of this kind from their tensors and attributes (no copies)."""
        return self.primitives(**tensors, **(attrs or {}), **extra)

    # --- the model file (radfield.model_file) ---------------------------------------------------

    def schema(self) -> dict[str, tuple]:
        """Required tensors -> shape after P, in the order a file's errors are reported ("K": the SH
        coefficients of the file's sh_degree; other letters: widths read off the first tensor that has them)."""
        return {**GEOMETRY, **self.own_params, **SH}

    def write_metadata(self, prims) -> dict[str, str]:
        """String metadata the model file stores for the kind's attributes."""
        return {}

    def read_metadata(self, path, meta: dict[str, str]) -> dict[str, Any]:
        """The attributes from a model file's metadata, validated (RadfieldError naming the file)."""
        return {}

    # The ranges a model file's values must keep (checked on load: radfield.model_file). Far from
    # what training and editing write (measured over every model of the test suite and the demo
    # scenes: |log s| <= 6.2, |μ| <= 1.1, |q| in [0.46, 4.2]), and chosen so that what the renderer
    # forms from them stays finite and normal in float32: s² and 1/s² for |log s| <= 25 (e^±50 ≈
    # 1e±22; a log scale of 100 made s = inf and the primitive silently vanish), |μ|² for |μ| <= 1e12,
    # q/|q| for |q| >= 1e-6 (|q|² underflows near 1e-19). ±25 still spans nm to 10⁵ km primitives,
    # whatever the unit of a dataset's world frame.
    LOG_SCALE_LIMIT = 25.0
    MEAN_LIMIT = 1e12
    QUAT_NORM_RANGE = (1e-6, 1e6)

    def check_values(self, prims) -> tuple[str, int, str] | None:
        """The first out-of-range value of `prims` as (tensor name, first bad primitive, why), or None.
        Called on finite values (the loader checks that first); a kind adds its own tensors' ranges
        to these of the shared geometry."""
        lim = self.LOG_SCALE_LIMIT
        bad = first_bad_row(prims.log_scales.abs() > lim)
        if bad is not None:
            value = prims.log_scales[bad][prims.log_scales[bad].abs() > lim][0]
            return "log_scales", bad, f"a log scale of {float(value):g} is outside [-{lim:g}, {lim:g}]"
        bad = first_bad_row(prims.means.abs() > self.MEAN_LIMIT)
        if bad is not None:
            return "means", bad, f"a coordinate beyond ±{self.MEAN_LIMIT:g}"
        lo, hi = self.QUAT_NORM_RANGE
        norm = prims.quats.double().norm(dim=-1)
        bad = first_bad_row((norm < lo) | (norm > hi))
        if bad is not None:
            return "quats", bad, f"norm {float(norm[bad]):g} is outside [{lo:g}, {hi:g}]"
        return None

    # --- rendering (core/render/rasterize.py) ---------------------------------------------------

    def at_view(self, prims, camera: "Camera"):
        """The primitives as `camera` sees them: render() (and the slow reference) calls this first
        and draws what it returns, so a kind conditioned on the view (e.g. on its time, `conditions`)
        hands the renderer primitives of a kind without conditions (differentiably: gradients reach
        its own tensors through the ones returned). Default: `prims` itself, at no cost."""
        return prims

    def at_conditions(self, prims, values: dict):
        """The static primitives of one value of each of its `conditions` (`values`: name -> value)
        for every view: what `radfield export --time T` writes. Default (no conditions): `prims`."""
        return prims

    def twin_view(self, prims, frame: ViewFrame) -> tuple[torch.Tensor, torch.Tensor, tuple]:
        """The torch twin's per-view preparation: (pixel bounds (P, 4) int64 x0 y0 x1 y1 inside the
        image, visible (P,) bool, the per-primitive view tensors (P, ...) its pair kernel takes)."""
        raise NotImplementedError(f"primitive kind {self.name!r} has no renderer (twin_view)")

    def pair_kernel(self, prims) -> Callable:
        """α of primitives (P,) over blocks of image points: kernel(u, v, intrinsics, *view) -> (P, A)."""
        raise NotImplementedError(f"primitive kind {self.name!r} has no renderer (pair_kernel)")

    def reference_alpha(self, prims, i: int, ray: "PixelRay", depth: float) -> float:
        """The slow reference's α of primitive i (camera-space depth `depth`) on one pixel's ray
        (float64, core/render/reference.py); a kind without an independent reference cannot be checked there."""
        raise NotImplementedError(f"primitive kind {self.name!r} has no reference renderer")

    # --- training (core/train/) ------------------------------------------------------------------

    def strategy(self, densify: dict, schedule, *, pixels: int | None, **common):
        """Population control from the train.densify config and its `schedule` (core/train/strategy.py:
        make_strategy); `pixels`: a training view's pixel count; `common`: extent, near, grow_scale,
        max_primitives, initial_count, attrs (the kind's attributes). Default: a fixed population."""
        from radfield.core.train.strategy import FixedPopulation

        return FixedPopulation()

    def regularisers(self, params: dict[str, torch.Tensor], cfg: dict) -> list[torch.Tensor]:
        """Weighted loss terms of the kind's own parameters, added after the anisotropy term."""
        return []

    def training_rules(self, cameras, cfg: dict, attrs: dict, near: float) -> list:
        """Projections applied after every optimiser step, in order (each has apply(params, step));
        the footprint floor of core/train/footprint.py follows them for every kind."""
        return []

    # --- initialisation (stages/init.py) ---------------------------------------------------------

    init_config_keys: tuple[str, ...] = ()    # pipeline config keys init_settings reads, besides `init`

    def init_settings(self, config: dict) -> dict[str, Any]:
        """What `initial_radius` and `from_points` read from the pipeline config (the `init` section
        and `init_config_keys`, which the init stage's cache key includes)."""
        return {}

    def initial_radius(self, spacing, settings: dict):
        """The radius of a new primitive whose neighbours lie `spacing` away (3DGS: the spacing)."""
        return spacing

    def from_points(self, geometry: dict[str, torch.Tensor], settings: dict, seed: int):
        """New primitives from their geometry (means, log_scales, quats, sh) and the kind's settings."""
        raise NotImplementedError(f"primitive kind {self.name!r} cannot be initialised from points")

    # --- editing (edit/) and delivery -----------------------------------------------------------

    def deformed(self, prims, idx: torch.Tensor, sub, a: torch.Tensor, scales: torch.Tensor,
                 new_scales: torch.Tensor, preserve_opacity: bool):
        """The kind's own tensors of rows `idx` under the affine maps x' = A x + b, A (S, 3, 3)
        float64 (edit/affine.py maps the geometry and SH): (prims, possibly with a field added,
        {name: new rows}). sub: prims.select(idx) in float64; scales, new_scales (S, 3) the
        ellipsoid's radii before and after. Default: nothing of its own changes."""
        return prims, {}

    def rotated(self, prims, rot: torch.Tensor) -> dict[str, torch.Tensor]:
        """The kind's own tensors under a similarity x' = s R x + t (edit/compose.py); default: unchanged."""
        return {}

    def halved(self, parents, offset: torch.Tensor, ratio: torch.Tensor) -> dict[str, torch.Tensor]:
        """The kind's own tensors of the halves of `parents` (edit/affine.py: split_primitives), each
        moved by `offset` (S, 3) from its parent's centre, max(s) shrunk by `ratio` (S,); default: the parents'."""
        return {}

    def check_combinable(self, a, b, where: str) -> None:
        """RadfieldError (one line) when two models of the kind cannot be joined into one."""

    def harmonise(self, a, b):
        """a and b brought to a common layout of the kind's own tensors before they are joined
        (b folded into a's attributes); default: as they are."""
        return a, b

    def combine_notes(self, a, b) -> dict[str, Any]:
        """What joining b into a changed, for the edit manifest."""
        return {}

    def peak_density(self, prims, samples: int = 128, seed: int = 0) -> torch.Tensor:
        """Per primitive (P,) its peak opacity-like level (edit/recolor.py: density_above)."""
        raise NotImplementedError(f"primitive kind {self.name!r} has no peak density")

    def to_gaussians(self, prims, components: int = 1):
        """The model as 3D Gaussians (delivery/export.py)."""
        raise RadfieldError(f"{self.name} primitives cannot be exported as 3D Gaussians")

    def bench_models(self, scene: dict[str, torch.Tensor], generator: torch.Generator) -> dict[str, Any]:
        """{variant: primitives} of bench-render's scene (means, log_scales, quats, sh of a radius s)."""
        return {}


# --- the registry --------------------------------------------------------------------------------

_KINDS: Registry[PrimitiveKind] = Registry("primitive kind")


def register(kind: PrimitiveKind) -> PrimitiveKind:
    """Make a kind known (by its name and its primitives' `kind` attribute, which must agree)."""
    if kind.primitives.kind != kind.name:
        raise ValueError(f"kind {kind.name!r}: its primitives say kind = {kind.primitives.kind!r}")
    return _KINDS.register(kind.name, kind)


def unregister(name: str) -> None:
    _KINDS.unregister(name)


def names() -> tuple[str, ...]:
    """The registered kinds, in registration order (neural, gaussian, then any added)."""
    return _KINDS.names()


def registered() -> tuple[PrimitiveKind, ...]:
    """The registered kinds, in registration order."""
    return _KINDS.values()


def get(name: str) -> PrimitiveKind:
    return _KINDS.get(name)


def of(prims) -> PrimitiveKind:
    """The kind of a primitives object."""
    return get(getattr(prims, "kind", type(prims).__name__))


# --- shared helpers: metadata and ellipsoid bounds ------------------------------------------------

def first_bad_row(mask: torch.Tensor) -> int | None:
    """The first primitive (row) of a (P, ...) bool mask with any True, or None."""
    rows = mask.reshape(len(mask), -1).any(1) if len(mask) else mask.new_zeros(0, dtype=torch.bool)
    hit = torch.nonzero(rows)
    return int(hit[0, 0]) if len(hit) else None


def int_metadata(path, meta: dict[str, str], key: str) -> int:
    try:
        return int(meta[key])
    except (KeyError, ValueError):
        raise RadfieldError(f"{path}: metadata {key!r} is missing or not an integer ({meta.get(key)!r})") from None


def float_metadata(path, meta: dict[str, str], key: str) -> float:
    """A positive finite number from the metadata (RadfieldError otherwise)."""
    try:
        value = float(meta[key])
    except (KeyError, ValueError):
        raise RadfieldError(f"{path}: metadata {key!r} is missing or not a number ({meta.get(key)!r})") from None
    if not value > 0 or value == float("inf"):
        raise RadfieldError(f"{path}: metadata {key!r} must be a positive number, got {value}")
    return value
