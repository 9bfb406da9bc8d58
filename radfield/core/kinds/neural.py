"""Splattable neural primitives (Splat the Net): the kind "neural".

Density inside the ellipsoid B(μ, R, s) (paper eq. 5-6): σ(x) = W2 · cos(ω0 (W1 u + b1)) + b2 with
u = (x − μ) / max(s), times the window 1.5 (1 − r²) where `window` is set (`density_window`). The
renderer integrates it in closed form along each pixel's chord (core/splat/kernels.py, eq. 7-9).
Everything the rest of radfield needs to know about the kind is said here (kinds/base.py lists
the hooks): its parameters and file metadata (ω0, window), its renderer hooks (the per-view frame
and MLP phases, the dual-conic bounds, the pair kernel and the fused CPU view), its population
control (the MLP-gradient strategy), regularisers and per-step projections (frequency cap,
non-negative density), its initialisation, and what edits and exports do to its MLP.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import partial

import torch

from radfield.core import backends
from radfield.core.backends import fused, gpu
from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.core.kinds.base import INITIAL_ALPHA, PrimitiveKind, Primitives, first_bad_row, float_metadata, register
from radfield.core.kinds.neural_density import neural_sigma, quadrature_optical_depth, unit_ball_samples
from radfield.core.splat.neural import density_weights, pair_alpha, view_tensors
from radfield.core.splat.sh import num_sh_coeffs
from radfield.core.splat.view import ViewFrame, ellipsoid_bounds
from radfield.errors import RadfieldError

DEFAULT_OMEGA0 = 30.0
DEFAULT_HIDDEN = 8
# a new primitive's b2: a ray through the centre crosses τ-length 2 (the diameter in units of
# max(s)) and the cos terms average out, so it sees opacity 1 − exp(−2 b2) = INITIAL_ALPHA
NEURAL_B2 = -math.log(1.0 - INITIAL_ALPHA) / 2.0


@dataclass
class NeuralPrimitives(Primitives):
    """Splattable neural primitives. Density inside the ellipsoid (radii s, paper eq. 5-6):
    σ(x) = w2 · cos(ω0 (w1 u + b1)) + b2,  u = (x − μ) / max(s), times the window 1.5 (1 − r²)
    where `window` is set (`density_window`)."""

    w1: torch.Tensor = None  # (P, N, 3)
    b1: torch.Tensor = None  # (P, N)
    w2: torch.Tensor = None  # (P, N)
    b2: torch.Tensor = None  # (P,)
    omega0: float = DEFAULT_OMEGA0
    # optional, written by `radfield edit --preserve-opacity` (edit/affine.py): per primitive the
    # symmetric rest-space metric G (xx yy zz xy xz yz) that scales the optical depth by √(d̂ᵀ G d̂)
    rest_metric: torch.Tensor | None = None  # (P, 6)
    # the density window (render.window, core/splat/kernels.py: windowed_optical_depth): σ(x) is taken
    # times 1.5 (1 − r²), r = |S⁻¹Rᵀ(x − μ)|, so it falls to 0 on the ellipsoid and a primitive's
    # silhouette is smooth; False: the paper's hard-edged ellipsoid. The model file's `window` key
    # (absent = False); map/to/select keep it.
    window: bool = field(default=False, kw_only=True)

    kind = "neural"

    @property
    def hidden(self) -> int:
        return self.w1.shape[1]


def siren_mlp_init(num: int, hidden: int = DEFAULT_HIDDEN, omega0: float = DEFAULT_OMEGA0, generator=None, dtype=torch.float32,
                   w1_bound: float = 1 / 3):
    """MLP weights as in the paper (§3.3, after SIREN): W1 ~ U(−1/3, 1/3), W2 ~ U(±√(6/N)/ω0), b1 ~ U(−1/3, 1/3).
    `w1_bound` replaces W1's 1/3: the initial frequency scale (each cosine starts at most
    ω0 · w1_bound · √3 rad per unit of u).

    b2 is returned as zeros; callers set it to the opacity level they want (see `density_offset_for_alpha`)."""
    u = lambda *shape: torch.rand(*shape, generator=generator, dtype=dtype) * 2 - 1
    w1 = u(num, hidden, 3) * w1_bound
    b1 = u(num, hidden) / 3
    w2 = u(num, hidden) * math.sqrt(6 / hidden) / omega0
    return w1, b1, w2, torch.zeros(num, dtype=dtype)


def random_neural(num: int, *, sh_degree: int = 0, hidden: int = DEFAULT_HIDDEN, omega0: float = DEFAULT_OMEGA0,
                  extent: float = 1.0, scale: float = 0.1, b2: float = 1.0, w2_amplitude: float = 0.3,
                  seed: int = 0, dtype=torch.float32) -> NeuralPrimitives:
    """Random primitives in a cube of half-size `extent` (for tests and benchmarks). W2 is drawn
    from U(±w2_amplitude), larger than the training init, so the cos terms visibly shape density."""
    g = torch.Generator().manual_seed(seed)
    w1, b1, _, _ = siren_mlp_init(num, hidden, omega0, g, dtype)
    return NeuralPrimitives(
        means=(torch.rand(num, 3, generator=g, dtype=dtype) * 2 - 1) * extent,
        log_scales=torch.log(scale * (0.5 + torch.rand(num, 3, generator=g, dtype=dtype))),
        quats=torch.randn(num, 4, generator=g, dtype=dtype),
        sh=torch.randn(num, num_sh_coeffs(sh_degree), 3, generator=g, dtype=dtype) * 0.5,
        w1=w1, b1=b1, w2=(torch.rand(num, hidden, generator=g, dtype=dtype) * 2 - 1) * w2_amplitude,
        b2=torch.full((num,), b2, dtype=dtype), omega0=omega0,
    )


def neural_radius_factor(window: bool) -> float:
    """k such that a neural primitive of radius k·d has a Gaussian of scale d's per-axis variance
    d²: 1/k² = E[x²] of the density profile in the unit ball (window 1.5 (1 − r²): 1/7; hard: 1/5)."""
    return math.sqrt(7.0) if window else math.sqrt(5.0)


# --- the torch twin's per-view preparation and pair kernel ---------------------------------------


def _fused_cpu_view(prims: NeuralPrimitives, frame: ViewFrame, colors: torch.Tensor, t_min: float):
    """The whole view on the fused CPU kernels: bounds and depth order, the neural frame and the
    compositing in C++ (core/backends/csrc/prepare_kernels.cpp, view_kernels.cpp); returns
    (Σ w c, Σ w z, T, counters, the number of visible primitives)."""
    camera = frame.camera
    bounds, ids = fused.neural_bounds(frame.means_cam, prims.log_scales, prims.quats, frame.w2c[:3, :3],
                                      frame.intrinsics, camera.width, camera.height, frame.near)
    m_cam, o_ell, w_cam, c, inv_smax = fused.neural_prep(prims, frame.campos, frame.c2w[:3, :3])
    view = (m_cam, o_ell, w_cam, c, *density_weights(prims, frame.campos - prims.means), inv_smax)
    out = fused.neural_view(bounds, ids, frame.intrinsics, camera.height, camera.width, t_min, colors, frame.depth,
                            *view, window=prims.window)
    return (*out, ids.numel())


# --- what an edit does to the MLP ------------------------------------------------------------------

def metric_matrix(v: torch.Tensor) -> torch.Tensor:
    """(P, 6) xx yy zz xy xz yz -> symmetric (P, 3, 3)."""
    xx, yy, zz, xy, xz, yz = v.unbind(-1)
    return torch.stack([xx, xy, xz, xy, yy, yz, xz, yz, zz], -1).reshape(-1, 3, 3)


def metric_vector(g: torch.Tensor) -> torch.Tensor:
    return torch.stack([g[:, 0, 0], g[:, 1, 1], g[:, 2, 2], g[:, 0, 1], g[:, 0, 2], g[:, 1, 2]], -1)


def pad_hidden(prims: NeuralPrimitives, hidden: int) -> NeuralPrimitives:
    """Neural primitives with zero units appended up to `hidden` (W2 = 0: the density is unchanged)."""
    extra = hidden - prims.hidden
    if extra <= 0:
        return prims
    out = prims.map(lambda x: x)
    out.w1 = torch.cat([prims.w1, prims.w1.new_zeros(len(prims), extra, 3)], 1)
    out.b1 = torch.cat([prims.b1, prims.b1.new_zeros(len(prims), extra)], 1)
    out.w2 = torch.cat([prims.w2, prims.w2.new_zeros(len(prims), extra)], 1)
    return out


def with_rest_metric(prims: NeuralPrimitives, needed: bool) -> NeuralPrimitives:
    """prims with a `rest_metric` (identity G = I for each primitive: unchanged optical depth) when
    `needed` and it has none, so that it joins a field edited with preserve_opacity."""
    if not needed or prims.rest_metric is not None:
        return prims
    out = prims.map(lambda x: x)
    out.rest_metric = prims.means.new_tensor([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]).expand(len(prims), 6).clone()
    return out


class NeuralKind(PrimitiveKind):
    name = "neural"
    primitives = NeuralPrimitives
    own_params = {"w1": ("N", 3), "b1": ("N",), "w2": ("N",), "b2": ()}
    lr_keys = {"w1": "mlp", "b1": "mlp", "w2": "mlp", "b2": "mlp"}
    # `rest_metric` (P, 6), written by `radfield edit` with preserve_opacity (edit/affine.py; docs/formats.md)
    optional = {"rest_metric": (6,)}
    attributes = ("omega0", "window")
    retrainable_locally = True
    bench_variants = ("neural", "neural-hard")

    # --- the model file: ω0 always, `window` ("1") only when set, so hard-edged files keep their bytes

    def write_metadata(self, prims) -> dict[str, str]:
        meta = {"omega0": repr(float(prims.omega0))}
        if prims.window:   # absent = the hard-edged ellipsoid: older files keep their bytes (and hash)
            meta["window"] = "1"
        return meta

    def read_metadata(self, path, meta: dict[str, str]) -> dict:
        omega0 = float_metadata(path, meta, "omega0")
        window = meta.get("window", "0")
        if window not in ("0", "1"):
            raise RadfieldError(f"{path}: metadata window={window!r} is not 0 or 1")
        return {"omega0": omega0, "window": window == "1"}

    # ω0·|W1 row|, a hidden unit's frequency in radians per unit of the primitive's own radius: at
    # most 16 in every model of the test suite (the frequency cap keeps trained models there); 1e4
    # is far beyond what any pixel grid resolves, and a wild value (1e30) makes cos() meaningless.
    MAX_FREQUENCY = 1e4

    def check_values(self, prims):
        out = super().check_values(prims)
        if out is not None:
            return out
        freq = prims.omega0 * prims.w1.double().norm(dim=-1)                 # (P, N)
        bad = first_bad_row(freq > self.MAX_FREQUENCY)
        if bad is not None:
            return "w1", bad, f"a frequency ω0·|w1| of {float(freq[bad].max()):g} exceeds {self.MAX_FREQUENCY:g}"
        if prims.rest_metric is not None:   # G = c² A⁻ᵀA⁻¹ (edit/affine.py) is positive definite
            info = torch.linalg.cholesky_ex(metric_matrix(prims.rest_metric.double())).info
            bad = first_bad_row(info != 0)
            if bad is not None:
                return "rest_metric", bad, "not positive definite (a rest-space metric must be)"
        return None

    # --- rendering

    def twin_view(self, prims, frame: ViewFrame):
        bounds, visible = ellipsoid_bounds(prims, frame)
        return bounds, visible, view_tensors(prims, frame.campos, frame.c2w[:3, :3])

    def pair_kernel(self, prims):
        return partial(pair_alpha, window=prims.window)

    def reference_alpha(self, prims, i, ray, depth):
        from radfield.core.splat.kernels import ALPHA_MAX

        optical_depth = quadrature_optical_depth(prims, i, ray.origin, ray.direction, l_min=ray.l_near)
        return min(ALPHA_MAX, 1.0 - math.exp(-max(0.0, optical_depth)))

    # --- training

    def strategy(self, densify: dict, schedule, *, pixels, **common):
        from radfield.core.train.strategy import NeuralStrategy, resolution_factor

        factor = resolution_factor(pixels)
        return NeuralStrategy(schedule, grad_threshold=factor * densify["grad_threshold"],
                              prune_scale=densify["prune_scale"], prune_threshold=factor * densify["prune_threshold"],
                              **common)

    def regularisers(self, params, cfg):
        from radfield.core.train.losses import density_magnitude, frequency_magnitude

        terms = []
        if cfg["lambda_w1"] > 0:
            terms.append(cfg["lambda_w1"] * frequency_magnitude(params["w1"]))
        if cfg["lambda_density"] > 0:
            terms.append(cfg["lambda_density"] * density_magnitude(params["w2"], params["b2"]))
        return terms

    def training_rules(self, cameras, cfg, attrs, near):
        from radfield.core.train.frequency import FrequencyCap
        from radfield.core.train.positivity import NonNegativeDensity

        # each W1 row's frequency stays below the primitive's pixel footprint (core/train/frequency.py),
        # then σ ≥ 0 everywhere in primitives seen from a narrow cone of views (core/train/positivity.py)
        return [FrequencyCap.for_training(cameras, cfg, omega0=attrs["omega0"], near=near),
                NonNegativeDensity.for_training(cameras, cfg, near=near)]

    # --- initialisation: SIREN-style MLP weights (paper §3.3) and b2 = NEURAL_B2

    init_config_keys = ("render.omega0", "render.hidden", "render.window")

    def init_settings(self, config):
        return {"hidden": config["render"]["hidden"], "omega0": config["render"]["omega0"],
                "window": config["render"]["window"], "w1_bound": config["init"]["w1_scale"],
                "neural_radius": config["init"]["neural_radius"]}

    def initial_radius(self, spacing, settings):
        # the spread of a Gaussian of scale d (stages/init.py): k·d with k = neural_radius_factor
        return spacing * (settings.get("neural_radius", 0.0) or neural_radius_factor(settings.get("window", False)))

    def from_points(self, geometry, settings, seed):
        hidden, omega0 = settings.get("hidden", DEFAULT_HIDDEN), settings.get("omega0", DEFAULT_OMEGA0)
        w1, b1, w2, b2 = siren_mlp_init(len(geometry["means"]), hidden, omega0,
                                        generator=torch.Generator().manual_seed(seed),
                                        w1_bound=settings.get("w1_bound", 1 / 3))
        return NeuralPrimitives(**geometry, w1=w1, b1=b1, w2=w2, b2=b2.fill_(NEURAL_B2), omega0=omega0,
                                window=settings.get("window", False))

    # --- editing: the density composes with the inverse map (edit/affine.py's module docstring)

    def deformed(self, prims, idx, sub, a, scales, new_scales, preserve_opacity):
        ratio = new_scales.amax(-1) / scales.amax(-1)                    # max(s') / max(s)
        a_inv = torch.linalg.inv(a)
        own = {"w1": ratio[:, None, None] * sub.w1 @ a_inv}              # W1' = (max s'/max s) W1 A⁻¹
        out = prims
        if preserve_opacity or prims.rest_metric is not None:
            if prims.rest_metric is None:                                # rest frame = the current one
                out = replace(prims, rest_metric=metric_vector(torch.eye(3, dtype=prims.means.dtype).expand(len(prims), 3, 3)))
            g_old = metric_matrix(out.rest_metric[idx].double())
            # G' = r² A⁻ᵀ G A⁻¹: composes with the metric of earlier edits
            own["rest_metric"] = metric_vector((ratio**2)[:, None, None] * a_inv.transpose(1, 2) @ g_old @ a_inv)
        return out, own

    def rotated(self, prims, rot):
        return {"w1": prims.w1 @ rot.T}   # σ'(x') = σ(x): W1' u' = W1 Rᵀ R u

    def halved(self, parents, offset, ratio):
        # u = (x − μ)/max(s) in each half: W1_c = r W1, b1_c = b1 + W1 (μ_c − μ)/max(s); W2, b2 scaled
        # by r keep the per-size optical depth (1/max(s)) ∫σ
        smax = parents.scales.amax(-1)
        return {"w1": parents.w1 * ratio[:, None, None],
                "b1": parents.b1 + (parents.w1 @ (offset / smax[:, None])[..., None])[..., 0],
                "w2": parents.w2 * ratio[:, None], "b2": parents.b2 * ratio}

    def check_combinable(self, a, b, where):
        """A model is drawn with one density, windowed 1.5 (1 − r²) σ or hard-edged σ: converting
        one into the other would need a retraining."""
        if a.window != b.window:
            name = lambda w: "windowed" if w else "hard-edged"
            raise RadfieldError(f"{where}: cannot combine a {name(a.window)} neural model (window={int(a.window)}) with a "
                                f"{name(b.window)} one (window={int(b.window)}); a model has one density window")

    def harmonise(self, a, b):
        """b's ω0 folded into its W1 and b1 (only ω0·W1 and ω0·b1 enter the density), both MLPs padded
        to the wider one, and both given a rest metric when one has it."""
        if b.omega0 != a.omega0:
            ratio = b.omega0 / a.omega0
            b = b.map(lambda x: x)
            b.w1, b.b1, b.omega0 = b.w1 * ratio, b.b1 * ratio, a.omega0
        hidden = max(a.hidden, b.hidden)
        a, b = pad_hidden(a, hidden), pad_hidden(b, hidden)
        return with_rest_metric(a, b.rest_metric is not None), with_rest_metric(b, a.rest_metric is not None)

    def combine_notes(self, a, b):
        return {"omega0_rescaled": [b.omega0, a.omega0]} if a.omega0 != b.omega0 else {}

    def peak_density(self, prims, samples=128, seed=0):
        """The max of σ at `samples` points of each ellipsoid (its centre, the ends of its axes and
        random points), in the primitive's own units (windowed where prims.window)."""
        with torch.no_grad():
            u = unit_ball_samples(samples, seed).to(prims.means.dtype)                 # (S, 3)
            rot = quat_to_rotmat(prims.quats)
            x = prims.means[:, None] + torch.einsum("pij,sj->psi", rot * prims.scales[:, None, :], u)
            sigma = neural_sigma(prims, x)                                             # (P, S)
        return sigma.max(1).values

    def to_gaussians(self, prims, components=1):
        # here, not at the top: moment_matching imports kinds.gaussian, which would register before this kind
        from radfield.core.kinds.moment_matching import gaussians_from_neural

        with torch.no_grad():
            return gaussians_from_neural(prims, components=components)

    def bench_models(self, scene, generator):
        w1, b1, w2, _ = siren_mlp_init(len(scene["means"]), generator=generator)
        # windowed, as a trained model with the defaults (render.window); "neural-hard": the paper's hard edge
        windowed = NeuralPrimitives(**scene, w1=w1, b1=b1, w2=w2 * 10, b2=torch.full((len(w1),), 1.0), window=True)
        return {"neural": windowed, "neural-hard": replace(windowed, window=False)}


NEURAL = register(NeuralKind())
backends.implement(backends.view_op("neural"), backends.FUSED_CPU, _fused_cpu_view)
backends.implement(backends.view_op("neural"), backends.TRITON, gpu.neural_view)
