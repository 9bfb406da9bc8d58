"""Time-conditioned primitives (Splat the Net, appendix C.1): the kinds "neural-dynamic" and "gaussian-dynamic".

A dynamic scene's views each show one moment ξ_t ∈ [0, 1] (Camera.conditions["time"]). Both kinds carry, per
primitive, a temporal colour: the zero-order SH coefficient is (paper eq. 10-12, n = l = 4)

    S(ξ) = S0 + Σ_{i=1..4} a_i ξ^i + Σ_{i=1..4} (b_i cos(i ω ξ) + c_i sin(i ω ξ))   per channel,

S0 the model's own sh DC and (a, b, c) the (P, 12, 3) tensor `sh_t`; ω (`time_frequency`, the
model file's metadata) is 1 as the paper writes it, over [0, 1] less than one period of the
Fourier terms, or 2π, one full period (issue 29 asks both to be measured).

- "neural-dynamic": splattable neural primitives whose density takes time as one more input
  (eq. 13, with the static model's ω0 placement of eq. 6),
      f_σ(x, ξ) = W2 cos(ω0 (W1 x̂ + ξ W_t + b1)) + b2,   W_t (P, N) the tensor `w_t`,
  so at time ξ a primitive IS a static neural primitive with phases b1' = b1 + ξ W_t.
- "gaussian-dynamic": the Gaussian baseline with the same temporal colour and a time-varying
  opacity, its logit o(ξ) = o + the same polynomial + Fourier form with coefficients `opacity_t` (P, 12).

The one seam the rest of radfield sees is `at_view` (kinds/base.py): render() and the slow
reference first turn the primitives into the static ones of the camera's time, so the closed-form line
integral, the fused CPU kernels and everything downstream apply unchanged, and autograd reaches
w_t, sh_t and opacity_t through b1, the SH DC and the opacity logits. Everything else is the
parent kind's (kinds/neural.py, kinds/gaussian.py), with the hooks the new tensors need.

Training (core/train/) needs nothing new: each view is rendered at its own time, population
control copies every parameter's rows (a clone or split child keeps its parent's W_t, sh_t,
opacity_t), checkpoints carry `time_frequency` with the other attributes. The neural kind's per-step
projections stay as they are: the frequency cap bounds ω0·|W1 row|, a spatial frequency that ξ W_t
(a phase constant in space) does not change, and σ ≥ b2 − ‖W2‖₁ (core/train/positivity.py) holds
whatever the phases, so at every time. The Gaussian kind's pruning and opacity reset read the
opacity's peak over time (`DynamicGaussianStrategy`). Edits map W1 and b1 as the parent's hooks do
and leave W_t (a phase: no affine map or halving of space changes it) and sh_t (the DC band,
rotation-invariant) alone, so an edit commutes with taking a moment.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, fields, replace

import torch

from radfield.core.kinds.base import first_bad_row, float_metadata, register
from radfield.core.kinds.gaussian import Gaussians, GaussianKind
from radfield.core.kinds.neural import NeuralKind, NeuralPrimitives
from radfield.core.splat.sh import join_sh, sh_parts
from radfield.errors import RadfieldError
from radfield.util.transfer import device_constants, to_device

DEGREE = 4                       # n = l = 4 (eq. 10-12): ξ^1..ξ^4, cos/sin(i ω ξ) for i = 1..4
TEMPORAL_TERMS = 3 * DEGREE      # a_1..a_4, b_1..b_4, c_1..c_4
PAPER_FREQUENCY = 1.0            # ω as eq. 11-12 write it
PERIOD_FREQUENCY = 2.0 * math.pi  # ω = 2π: the Fourier terms span one period over [0, 1]
DEFAULT_TIME_FREQUENCY = PAPER_FREQUENCY
# |coefficient| a model file may hold: trained values are O(1) logits and SH units; 1e4 is far
# beyond anything a colour or an opacity needs and keeps every S(ξ) finite in float32
MAX_TEMPORAL = 1e4
# ω0·|W_t|: the phase a hidden unit turns through over [0, 1], as the spatial frequency's bound
MAX_TIME_PHASE = NeuralKind.MAX_FREQUENCY
PEAK_TIMES = 9                   # moments at which peak densities/opacities are taken (0, 1/8, ..., 1)


def temporal_basis(xi: float, frequency: float) -> tuple[float, ...]:
    """φ(ξ) (12,) with S(ξ) − S0 = φ(ξ) · (a, b, c) (eq. 10-12): ξ^i, cos(i ω ξ), sin(i ω ξ), i = 1..4."""
    return (tuple(xi**i for i in range(1, DEGREE + 1))
            + tuple(math.cos(i * frequency * xi) for i in range(1, DEGREE + 1))
            + tuple(math.sin(i * frequency * xi) for i in range(1, DEGREE + 1)))


def temporal_offset(coeffs: torch.Tensor, xi: float, frequency: float) -> torch.Tensor:
    """The temporal term φ(ξ) · coeffs of coefficients (P, 12, ...) at time ξ: (P, ...)."""
    phi = coeffs.new_tensor(temporal_basis(xi, frequency))
    return torch.tensordot(phi, coeffs, dims=([0], [1]))


# The per-view forms below are the training step's (bench-train: the cost of time): each moment's
# basis is built once per (ξ, ω, dtype, device) and the temporal term is one matrix product with
# the coefficients as they are stored (a view, no copy), fused with the addition of the static term.

def basis_vector(xi: float, frequency: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """φ(ξ) (12,), for o + opacity_t φ(ξ) as one matrix-vector product (cached; callers never write to it)."""
    return device_constants(temporal_basis(xi, frequency), dtype, device)


@functools.lru_cache(maxsize=1024)
def colour_basis(xi: float, frequency: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """φ(ξ) ⊗ I₃ (36, 3): sh_t viewed as (P, 36) (term-major, channel-minor) times it is φ(ξ) · sh_t (P, 3)."""
    with torch.inference_mode(False):
        phi = torch.tensor(temporal_basis(xi, frequency), dtype=torch.float64)
        return to_device(torch.kron(phi[:, None], torch.eye(3, dtype=torch.float64)), device, dtype)


def view_time(camera) -> float:
    """The camera's time, checked: a dynamic model is drawn at one moment ξ_t ∈ [0, 1]."""
    if camera.conditions.get("time") is None:
        raise RadfieldError("this model is dynamic: give a time (--time T)")
    xi = float(camera.conditions["time"])
    if not 0.0 <= xi <= 1.0:   # also NaN
        raise RadfieldError(f"time {xi:g} of view {camera.name!r} is outside [0, 1] (a dynamic model's times)")
    return xi


def sh_at_time(prims, xi: float) -> torch.Tensor:
    """The SH coefficients (P, K, 3) at time ξ: S(ξ) as the DC band, the other bands as they are.
    Built with join_sh, so the fused colour op reads (DC, rest) in place as in static training."""
    parts = sh_parts(prims.sh)
    dc, rest = parts if parts is not None else (prims.sh[:, :1], prims.sh[:, 1:])
    n, sh_t = len(prims), prims.sh_t
    basis = colour_basis(xi, prims.time_frequency, sh_t.dtype, sh_t.device)
    # S(ξ) = S0 + φ(ξ) · (a, b, c) (eq. 10-12): one addmm
    return join_sh(torch.addmm(dc.reshape(n, 3), sh_t.reshape(n, TEMPORAL_TERMS * 3), basis).view(n, 1, 3), rest)


def static_fields(prims, static_type: type) -> dict:
    """The fields of `prims` that its static parent dataclass has (the same tensors, no copies)."""
    return {f.name: getattr(prims, f.name) for f in fields(static_type)}


def check_temporal(prims, names: tuple[str, ...]):
    """The first temporal coefficient beyond ±MAX_TEMPORAL, as check_values reports it."""
    for name in names:
        t = getattr(prims, name)
        bad = first_bad_row(t.abs() > MAX_TEMPORAL)
        if bad is not None:
            return name, bad, f"a temporal coefficient beyond ±{MAX_TEMPORAL:g}"
    return None


def read_time_frequency(path, meta: dict[str, str]) -> float:
    return float_metadata(path, meta, "time_frequency")


TIME_CONFIG_KEYS = ("render.time_frequency",)   # the pipeline key of ω (radfield/pipeline.yaml)


def time_settings(config: dict) -> dict:
    """The init settings both dynamic kinds add to their parent's: ω of eq. 11-12."""
    return {"time_frequency": float(config["render"]["time_frequency"])}


def check_same_frequency(a, b, where: str) -> None:
    if a.time_frequency != b.time_frequency:
        raise RadfieldError(f"{where}: cannot combine dynamic models of temporal frequencies ω = {a.time_frequency:g} "
                            f"and {b.time_frequency:g}; their colour over time has different bases")


# --- neural primitives with time (eq. 10-13) ---------------------------------------------------------

@dataclass
class DynamicNeuralPrimitives(NeuralPrimitives):
    """Neural primitives whose density phases move with time (b1 + ξ W_t, eq. 13) and whose SH DC
    follows S(ξ) (eq. 10-12)."""

    w_t: torch.Tensor = None    # (P, N) temporal weights W_t
    sh_t: torch.Tensor = None   # (P, 12, 3) temporal colour a_1..4, b_1..4, c_1..4
    time_frequency: float = field(default=DEFAULT_TIME_FREQUENCY, kw_only=True)   # ω of eq. 11-12

    kind = "neural-dynamic"


class DynamicNeuralKind(NeuralKind):
    name = "neural-dynamic"
    primitives = DynamicNeuralPrimitives
    own_params = {**NeuralKind.own_params, "w_t": ("N",), "sh_t": (TEMPORAL_TERMS, 3)}
    # W_t is a phase of the density MLP (its rate); sh_t offsets the SH DC (its rate)
    lr_keys = {**NeuralKind.lr_keys, "w_t": "mlp", "sh_t": "sh_dc"}
    attributes = NeuralKind.attributes + ("time_frequency",)
    conditions = ("time",)
    # no one density σ(x) over time: the boolean and remesh retraining (edit/retrain.py) refuse it
    retrainable_locally = False
    bench_variants = ("neural-dynamic",)

    def at_view(self, prims, camera):
        """The static neural primitives of the camera's time ξ: b1 + ξ W_t (eq. 13), S(ξ) as the DC (eq. 10-12)."""
        return self.at_time(prims, view_time(camera))

    def at_time(self, prims, xi: float) -> NeuralPrimitives:
        return NeuralPrimitives(**{**static_fields(prims, NeuralPrimitives),
                                   "b1": torch.add(prims.b1, prims.w_t, alpha=xi), "sh": sh_at_time(prims, xi)})

    def at_conditions(self, prims, values):
        return self.at_time(prims, values["time"])

    # --- the model file: the parent's metadata plus ω of eq. 11-12

    def write_metadata(self, prims):
        return {**super().write_metadata(prims), "time_frequency": repr(float(prims.time_frequency))}

    def read_metadata(self, path, meta):
        return {**super().read_metadata(path, meta), "time_frequency": read_time_frequency(path, meta)}

    def check_values(self, prims):
        out = super().check_values(prims)
        if out is not None:
            return out
        phase = prims.omega0 * prims.w_t.double().abs()
        bad = first_bad_row(phase > MAX_TIME_PHASE)
        if bad is not None:
            return "w_t", bad, f"a temporal phase ω0·|w_t| of {float(phase[bad].max()):g} exceeds {MAX_TIME_PHASE:g}"
        return check_temporal(prims, ("sh_t",))

    # --- initialisation: the parent's settings plus ω (render.time_frequency)

    init_config_keys = NeuralKind.init_config_keys + TIME_CONFIG_KEYS

    def init_settings(self, config):
        return {**super().init_settings(config), **time_settings(config)}

    def from_points(self, geometry, settings, seed):
        # W_t = 0 and sh_t = 0: the model starts static, every moment the static initialisation
        # (random W_t would scramble each unit's phase over time by ω0·W_t, tens of radians); the
        # gradients of W_t (ξ × that of b1) and sh_t (φ(ξ) × that of the DC) differ from moment to
        # moment, so the views' differences over time drive them away from zero
        static = super().from_points(geometry, settings, seed)
        n, hidden = len(static), static.hidden
        return DynamicNeuralPrimitives(**static_fields(static, NeuralPrimitives),
                                       w_t=torch.zeros(n, hidden), sh_t=torch.zeros(n, TEMPORAL_TERMS, 3),
                                       time_frequency=settings.get("time_frequency", DEFAULT_TIME_FREQUENCY))

    # --- editing: W_t is a phase (unchanged by affine maps and halving: the parent's hooks map
    # W1 and b1 only, and W_t and sh_t ride along); joining models folds ω0 and pads the MLP

    def check_combinable(self, a, b, where):
        super().check_combinable(a, b, where)
        check_same_frequency(a, b, where)

    def harmonise(self, a, b):
        ratio = b.omega0 / a.omega0   # only ω0·W_t enters the density, as ω0·W1 and ω0·b1
        a, b = super().harmonise(a, b)
        if ratio != 1.0:
            b = replace(b, w_t=b.w_t * ratio)
        return pad_w_t(a), pad_w_t(b)

    def peak_density(self, prims, samples=128, seed=0):
        """The max over PEAK_TIMES moments of the static peak density."""
        peaks = [super(DynamicNeuralKind, self).peak_density(self.at_time(prims, xi), samples, seed)
                 for xi in peak_times()]
        return torch.stack(peaks).amax(0)

    def to_gaussians(self, prims, components=1):
        raise RadfieldError(f"a dynamic model ({self.name}) is exported at one moment: give a time (--time T)")

    def bench_models(self, scene, generator):
        """The static "neural" bench model with random W_t and temporal colour (bench-train's cost of time)."""
        static = NeuralKind.bench_models(self, scene, generator)["neural"]
        n, hidden = len(static), static.hidden
        return {"neural-dynamic": DynamicNeuralPrimitives(
            **static_fields(static, NeuralPrimitives), w_t=(torch.rand(n, hidden, generator=generator) * 2 - 1) / 3,
            sh_t=0.1 * torch.randn(n, TEMPORAL_TERMS, 3, generator=generator))}


def pad_w_t(prims: DynamicNeuralPrimitives) -> DynamicNeuralPrimitives:
    """W_t padded with zeros to the MLP's width (after kinds/neural.py: pad_hidden)."""
    extra = prims.hidden - prims.w_t.shape[1]
    if extra <= 0:
        return prims
    return replace(prims, w_t=torch.cat([prims.w_t, prims.w_t.new_zeros(len(prims), extra)], 1))


def peak_times() -> list[float]:
    return [k / (PEAK_TIMES - 1) for k in range(PEAK_TIMES)]


# --- Gaussians with time (the baseline) -------------------------------------------------------------

@dataclass
class DynamicGaussians(Gaussians):
    """3D Gaussians with the temporal colour of eq. 10-12 and a time-varying opacity logit
    o(ξ) = o + φ(ξ) · opacity_t."""

    sh_t: torch.Tensor = None        # (P, 12, 3) temporal colour
    opacity_t: torch.Tensor = None   # (P, 12) temporal opacity logit
    time_frequency: float = field(default=DEFAULT_TIME_FREQUENCY, kw_only=True)

    kind = "gaussian-dynamic"


class DynamicGaussianKind(GaussianKind):
    name = "gaussian-dynamic"
    primitives = DynamicGaussians
    own_params = {**GaussianKind.own_params, "sh_t": (TEMPORAL_TERMS, 3), "opacity_t": (TEMPORAL_TERMS,)}
    lr_keys = {**GaussianKind.lr_keys, "sh_t": "sh_dc", "opacity_t": "opacities"}
    attributes = GaussianKind.attributes + ("time_frequency",)
    conditions = ("time",)
    exact_gaussians = False   # only its moments are 3D Gaussians
    bench_variants = ("gaussian-dynamic",)

    def at_view(self, prims, camera):
        return self.at_time(prims, view_time(camera))

    def at_time(self, prims, xi: float) -> Gaussians:
        opacity_t = prims.opacity_t
        opacities = torch.addmv(prims.opacities, opacity_t,
                                basis_vector(xi, prims.time_frequency, opacity_t.dtype, opacity_t.device))
        return Gaussians(**{**static_fields(prims, Gaussians), "opacities": opacities, "sh": sh_at_time(prims, xi)})

    def at_conditions(self, prims, values):
        return self.at_time(prims, values["time"])

    def write_metadata(self, prims):
        return {**super().write_metadata(prims), "time_frequency": repr(float(prims.time_frequency))}

    def read_metadata(self, path, meta):
        return {**super().read_metadata(path, meta), "time_frequency": read_time_frequency(path, meta)}

    def check_values(self, prims):
        return super().check_values(prims) or check_temporal(prims, ("sh_t", "opacity_t"))

    def strategy(self, densify, schedule, *, pixels, **common):
        """3DGS's adaptive density control on the opacity's peak over time (prune, reset)."""
        gaussian = densify["gaussian"]
        return dynamic_gaussian_strategy()(schedule, grad_threshold=gaussian["grad_threshold"],
                                       prune_scale=gaussian["prune_scale"], min_opacity=gaussian["min_opacity"],
                                       opacity_reset_every=gaussian["opacity_reset_every"], **common)

    init_config_keys = GaussianKind.init_config_keys + TIME_CONFIG_KEYS

    def init_settings(self, config):
        return {**super().init_settings(config), **time_settings(config)}

    def from_points(self, geometry, settings, seed):
        # sh_t = 0, opacity_t = 0: the model starts static (every moment the 3DGS initialisation)
        static = super().from_points(geometry, settings, seed)
        n = len(static)
        return DynamicGaussians(**static_fields(static, Gaussians), sh_t=torch.zeros(n, TEMPORAL_TERMS, 3),
                                opacity_t=torch.zeros(n, TEMPORAL_TERMS),
                                time_frequency=settings.get("time_frequency", DEFAULT_TIME_FREQUENCY))

    def check_combinable(self, a, b, where):
        check_same_frequency(a, b, where)

    def peak_density(self, prims, samples=128, seed=0):
        return torch.sigmoid(peak_opacity_logit(prims.opacities.detach(), prims.opacity_t.detach(), prims.time_frequency))

    def to_gaussians(self, prims, components=1):
        raise RadfieldError(f"a dynamic model ({self.name}) is exported at one moment: give a time (--time T)")

    def bench_models(self, scene, generator):
        """The static "gaussian" bench model with random temporal colour and opacity."""
        static = GaussianKind.bench_models(self, scene, generator)["gaussian"]
        n = len(static)
        return {"gaussian-dynamic": DynamicGaussians(
            **static_fields(static, Gaussians), sh_t=0.1 * torch.randn(n, TEMPORAL_TERMS, 3, generator=generator),
            opacity_t=0.1 * torch.randn(n, TEMPORAL_TERMS, generator=generator))}


def peak_opacity_logit(opacities: torch.Tensor, opacity_t: torch.Tensor, frequency: float,
                       times: list[float] | None = None) -> torch.Tensor:
    """The largest opacity logit (P,) over `times` (default: the PEAK_TIMES moments)."""
    times = peak_times() if times is None else times
    return torch.stack([opacities + temporal_offset(opacity_t, xi, frequency) for xi in times]).amax(0)


# moments (0, 0.01, ..., 1) at which population control takes a Gaussian's peak opacity: the
# logit's temporal terms move by well under a logit between them for trained coefficients, where
# a closed-form bound over [0, 1] (Σ max(a_i, 0) + Σ √(b_i² + c_i²)) overshot the peak by a median
# 7.5 logits on smoke: its reset left most Gaussians far below 0.01 at every moment, too faint to
# recover, and its pruning kept them (docs/usage.md "Dynamic scenes")
STRATEGY_TIMES = 101


def strategy_times() -> list[float]:
    return [k / (STRATEGY_TIMES - 1) for k in range(STRATEGY_TIMES)]


@functools.cache
def dynamic_gaussian_strategy() -> type:
    """GaussianStrategy with the opacity taken at its peak over time (core/train/strategy.py is
    imported on first use: it imports the kinds)."""
    from radfield.core.train.strategy import GaussianStrategy

    class DynamicGaussianStrategy(GaussianStrategy):
        """3DGS's control on the opacity's peak over time (STRATEGY_TIMES moments, ω from the
        kind's attributes): a Gaussian opaque at one moment only is not pruned for being
        transparent at the others, one transparent at every moment is, and the opacity reset lowers
        o so that the peak is the reset value (the temporal shape in opacity_t is kept), as 3DGS's
        reset leaves a static Gaussian at 0.01, not below it.

        A clone or split child starts from its parent's Adam moments: with zeros (3DGS's rule, long
        after the bias correction has faded) Adam's first ~100 steps of a new row are 3-6 × the
        rate, and the 12 temporal coefficients of a logit, moving together, swung it by tens of
        logits: most Gaussians went transparent at every moment (smoke: 8031 of 9235, held-out
        PSNR 10 dB below the budgeted runs that never grow; docs/usage.md "Dynamic scenes")."""

        inherited_moments = GAUSSIAN_DYNAMIC.param_names()

        def opacity_logits(self, params):
            return peak_opacity_logit(params["opacities"].detach(), params["opacity_t"].detach(),
                                      self.attrs["time_frequency"], strategy_times())

        def reset_opacities(self, params, ceiling):
            params["opacities"].sub_((self.opacity_logits(params) - ceiling).clamp_min(0.0))

    return DynamicGaussianStrategy


NEURAL_DYNAMIC = register(DynamicNeuralKind())
GAUSSIAN_DYNAMIC = register(DynamicGaussianKind())
