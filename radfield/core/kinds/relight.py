"""Relightable primitives (Splat the Net, appendix C.2): the kinds "neural-relight" and "gaussian-relight".

A one-light-at-a-time capture lights each view by one known light (Camera.conditions["light"]: a point light at
p_light or a directional one, of known intensity). Both kinds replace the SH colour by a constant
colour plus a small neural colour field per primitive (eq. 14),

    c = (c_dc + c_θ(d, d_l)) · E,    c_θ(d, d_l) = W2 softplus(W1 [Rᵀd, Rᵀd_l] + b1) + b2,

- c_dc: the SH colour of the model's own `sh` (its DC band is eq. 14's constant colour, taken from
  the points' colours as the static kinds' DC). The init stage gives a new model the DC band only
  (`init_settings`' sh_degree, whatever train.sh_degree; the train stage trains the init model's
  SH degree): eq. 14 as written, and the SH warm-up schedule could not reach higher bands anyway
  (at_view runs before render()'s degree limit). Measured on `demo-scene olat` (64 px, 3000
  steps, seeds 0 and 1): held-out PSNR 27.00 / 26.98 dB at degree 0 against 26.90 / 26.94 at
  degree 3 (then with H = 8: 137 parameters a primitive against 182; docs/usage.md "Relighting"). A model
  file with higher bands (made by hand) adds them, the same colour as the static kind's;
- d: the unit direction from the camera to μ, d_l the unit direction from μ towards the light
  (normalise(p_light − μ), or −direction for a directional light), both turned into the
  primitive's own frame by Rᵀ (R from its quaternion): a cage edit or a similarity that turns the
  primitive turns its colour field with it, as rotating the SH does for the SH colour, and the
  network's tensors never change under an edit (`rotated`, `deformed`, `halved`: the parent's);
- E: the light's irradiance at μ, intensity / |p_light − μ|² or the intensity: known, not learned;
- the network (`color_w1` (P, H, 6), `color_b1` (P, H), `color_w2` (P, 3, H), `color_b2` (P, 3)),
  softplus hidden units (measured against ReLU, tanh and cos on per-primitive Lambert + Blinn-Phong
  colour functions of (d, d_l): softplus, ReLU and tanh fit held-out directions alike and cos worse;
  softplus is smooth, so a highlight moves smoothly with the light, and has no dead units), H = 12
  by default: a neural primitive then has 10 + 3 + 41 + 123 = 177 parameters at SH degree 0 (eq.
  14 as written) against the static kind's 99, within the 2× the issue allows. Measured on `olat`
  (64 px, 3000 steps, the network at the density MLP's rate): held-out PSNR 27.00 dB at H = 8,
  27.20 at 12, 27.25 at 14 (197 parameters, the 2× limit): 12 takes most of the gain with room
  under the limit. The network learns at train.lr.color, 3× the density MLP's rate (27.54 dB
  against 27.20 at 1×; 0.5×: 26.44, 10×: 27.34): at 1× 3000 steps leave it far from converged
  (6000 steps at 1×: 27.77).

Where along a ray x is taken: at the primitive's centre μ (x̂ = 0), so the network takes d and d_l
only. radfield composites one colour per primitive per view (the SH colour, and every fused and
GPU kernel's compositing); a colour per (pixel, primitive) pair would need a new compositing kernel
on every backend, for primitives that cover 1-2 pixels in a trained model. The difference to the
exact volume-rendering integral with colour varying along the ray is measured in
tests/test_relight_kinds.py (test_the_centre_colour_against_quadrature_of_a_colour_varying_along_the_ray).

The one seam the rest of radfield sees is `at_view` (kinds/base.py): render() and the slow
reference first turn the primitives into static ones whose SH is degree 0 with the DC of the
view's colour ((c − 0.5)/C0: core/splat/sh.py draws max(C0·DC + 0.5, 0)), so the closed-form line
integral, the fused CPU kernels and everything downstream apply unchanged, and autograd reaches
c_dc, the network, μ and q through that DC. On the CPU that DC is one fused op with a hand-written
backward for models of SH degree 0 (backend op relight_view_dc, core/backends/csrc/relight_kernels.cpp,
tests/test_relight_fused.py; 10k primitives, 64 px, one thread, two runs: a degree-0 training step
1.15–1.21× the static neural kind's instead of 1.76–1.90×, gaussian-relight 1.22–1.25× instead of
2.10–2.13×); `relit_colour` is its twin.
`at_light(prims, light)` gives the static model of one light for every view (the colour over
directions fitted by SH of degree 3), which is what an export under a light writes. Training needs
nothing new (the network's rows are copied by population control as every parameter's; it learns
at train.lr.color).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch

from radfield.core import backends
from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.core.kinds.base import first_bad_row, register
from radfield.core.kinds.gaussian import Gaussians, GaussianKind
from radfield.core.kinds.neural import NeuralKind, NeuralPrimitives
from radfield.core.splat.sh import C0, fibonacci_sphere, sh_basis
from radfield.errors import RadfieldError
from radfield.util.transfer import to_device

DEFAULT_COLOR_HIDDEN = 12       # H: hidden units of a primitive's colour network (module docstring)
SH_DEGREE = 0                   # a new model's SH: c_dc only, eq. 14 as written (module docstring, measured)
NETWORK_INPUTS = 6              # (Rᵀd, Rᵀd_l)
# |weight| a model file may hold: trained weights are O(1); 1e4 is far beyond any colour and keeps
# the network finite in float32
MAX_NETWORK_WEIGHT = 1e4
EXPORT_SH_DEGREE = 3            # at_light fits each primitive's colour over directions by SH of this degree
EXPORT_DIRECTIONS = 64          # ... on this many directions (≥ 16 coefficients, well conditioned)
EXPORT_CHUNK = 4096             # primitives fitted at once
NETWORK = {"color_w1": ("H", NETWORK_INPUTS), "color_b1": ("H",), "color_w2": (3, "H"), "color_b2": (3,)}


# --- the light and the colour field (eq. 14) --------------------------------------------------------

def view_light(camera):
    """The camera's light, checked: a relightable model is drawn under one known light."""
    if camera.conditions.get("light") is None:
        raise RadfieldError("this model is relightable: give a light (--light X,Y,Z or --light-dir X,Y,Z)")
    return camera.conditions["light"]


def light_at_primitives(means: torch.Tensor, light) -> tuple[torch.Tensor, torch.Tensor]:
    """(d_l (P, 3): the unit direction from each centre towards the light, E (P, 1): the light's
    irradiance there, intensity / r² for a point light at distance r, the intensity for a directional one)."""
    if light.position is not None:
        to_light = to_device(torch.tensor(light.position, dtype=means.dtype), means.device) - means
        r2 = (to_light * to_light).sum(-1, keepdim=True)
        return to_light / torch.sqrt(r2), light.intensity / r2
    towards = -to_device(torch.tensor(light.direction, dtype=means.dtype), means.device)   # it shines along `direction`
    return towards.expand_as(means), means.new_full((len(means), 1), light.intensity)


def color_network(prims, d_own: torch.Tensor, dl_own: torch.Tensor) -> torch.Tensor:
    """c_θ(d, d_l) (P, A, 3) of directions (P, A, 3) already in each primitive's own frame."""
    # products summed by broadcasting, not bmm: bmm of P tiny matrices made at_view 2.3× slower on the CPU
    x = torch.cat([d_own, dl_own], -1)                                          # (P, A, 6)
    hidden = torch.nn.functional.softplus(batched_matvec(prims.color_w1, x) + prims.color_b1[:, None])
    return batched_matvec(prims.color_w2, hidden) + prims.color_b2[:, None]    # (P, A, 3)


def batched_matvec(m: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """M_p x_pa (P, A, R) of matrices (P, R, C) and vectors (P, A, C)."""
    return (m[:, None] * x[:, :, None, :]).sum(-1)


def to_own_frame(rot: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Rᵀ d of world directions (P, A, 3), R (P, 3, 3) the primitives' rotations: their own frame,
    which edits turn with them."""
    return batched_matvec(rot.transpose(1, 2), dirs)


def relit_colour(prims, view_dirs: torch.Tensor, light) -> torch.Tensor:
    """c = (c_dc + c_θ(d, d_l)) · E (eq. 14) (P, A, 3) along unit view directions d (P, A, 3)
    (camera to μ, world frame); c_dc the SH colour of the model's own bands, before any clamp."""
    d_l, irradiance = light_at_primitives(prims.means, light)
    basis = sh_basis(view_dirs, prims.sh_degree)                                # (P, A, K)
    c_dc = batched_matvec(prims.sh.transpose(1, 2), basis) + 0.5               # as eval_sh, at A directions
    rot = quat_to_rotmat(prims.quats)
    dl_own = to_own_frame(rot, d_l[:, None]).expand_as(view_dirs)
    return (c_dc + color_network(prims, to_own_frame(rot, view_dirs), dl_own)) * irradiance[:, None]


def dc_of_colour(colour: torch.Tensor) -> torch.Tensor:
    """The degree-0 SH (P, 1, 3) that core/splat/sh.py draws as this colour (P, 3): max(C0·DC + 0.5, 0)."""
    return ((colour - 0.5) / C0)[:, None, :]


def view_sh(prims, camera) -> torch.Tensor:
    """The degree-0 SH of each primitive's colour in this view: d = normalise(μ − o)."""
    campos = to_device(camera.c2w[:3, 3], prims.means.device, prims.means.dtype)
    light = view_light(camera)
    # the same in one op with a hand-written backward (fused: core/backends/csrc/relight_kernels.cpp),
    # for the DC band alone (the kinds train degree 0); None: the torch twin below
    fused_dc = backends.kernel(backends.Op.RELIGHT_VIEW_DC, prims.means.device, prims.means.dtype)
    if fused_dc is not None and prims.sh_degree == 0:
        return fused_dc(prims.means, prims.quats, prims.sh, prims.color_w1, prims.color_b1, prims.color_w2,
                        prims.color_b2, campos, light)
    d = torch.nn.functional.normalize(prims.means - campos, dim=-1)
    return dc_of_colour(relit_colour(prims, d[:, None], light)[:, 0])


def light_sh(prims, light, degree: int = EXPORT_SH_DEGREE) -> torch.Tensor:
    """SH (P, (degree+1)², 3) whose colour over view directions fits each primitive's colour under
    `light` (least squares on EXPORT_DIRECTIONS directions; the rendered colour is SH + 0.5)."""
    dirs = fibonacci_sphere(EXPORT_DIRECTIONS).to(device=prims.means.device, dtype=prims.means.dtype)
    fit = torch.linalg.pinv(sh_basis(dirs, degree))                             # (K, D)
    # in chunks: the colours at D directions take D times a view's memory
    chunks = [fit @ (relit_colour(prims.select(slice(i, i + EXPORT_CHUNK)), dirs.expand(min(EXPORT_CHUNK, len(prims) - i),
                                                                                         -1, -1), light) - 0.5)
              for i in range(0, len(prims), EXPORT_CHUNK)]
    return torch.cat(chunks) if chunks else prims.sh.new_zeros(0, (degree + 1) ** 2, 3)


def static_fields(prims, static_type: type) -> dict:
    """The fields of `prims` that its static parent dataclass has (the same tensors, no copies)."""
    return {f.name: getattr(prims, f.name) for f in fields(static_type)}


def init_network(num: int, hidden: int, seed: int, dtype=torch.float32) -> dict[str, torch.Tensor]:
    """W1, b1 ~ U(−1, 1) (the hidden units span the unit inputs' range), W2 = b2 = 0: the network's
    output is 0, so a new model draws exactly its points' colours (the static kind's start) and
    the views' differences under the lights grow the network from there (W2's gradient is the
    hidden units' response, non-zero from the first step)."""
    g = torch.Generator().manual_seed(seed)
    u = lambda *shape: torch.rand(*shape, generator=g, dtype=dtype) * 2 - 1
    return {"color_w1": u(num, hidden, NETWORK_INPUTS), "color_b1": u(num, hidden),
            "color_w2": torch.zeros(num, 3, hidden, dtype=dtype), "color_b2": torch.zeros(num, 3, dtype=dtype)}


def check_network(prims):
    """The first network weight beyond ±MAX_NETWORK_WEIGHT, as check_values reports it."""
    for name in NETWORK:
        bad = first_bad_row(getattr(prims, name).abs() > MAX_NETWORK_WEIGHT)
        if bad is not None:
            return name, bad, f"a colour-network weight beyond ±{MAX_NETWORK_WEIGHT:g}"
    return None


def pad_network(prims, hidden: int):
    """The colour network widened to `hidden` units with W2 = 0 columns (the colour is unchanged)."""
    extra = hidden - prims.color_w1.shape[1]
    if extra <= 0:
        return prims
    n = len(prims)
    return replace(prims, color_w1=torch.cat([prims.color_w1, prims.color_w1.new_zeros(n, extra, NETWORK_INPUTS)], 1),
                   color_b1=torch.cat([prims.color_b1, prims.color_b1.new_zeros(n, extra)], 1),
                   color_w2=torch.cat([prims.color_w2, prims.color_w2.new_zeros(n, 3, extra)], 2))


def harmonise_networks(a, b):
    hidden = max(a.color_w1.shape[1], b.color_w1.shape[1])
    return pad_network(a, hidden), pad_network(b, hidden)


def no_export_without_light(name: str):
    raise RadfieldError(f"a relightable model ({name}) is exported under one light: give a light "
                        f"(--light X,Y,Z or --light-dir X,Y,Z)")


def network_count(hidden: int = DEFAULT_COLOR_HIDDEN) -> int:
    """Parameters of one primitive's colour network: 6H + H + 3H + 3."""
    return hidden * NETWORK_INPUTS + hidden + 3 * hidden + 3


# --- the hooks both relightable kinds share ---------------------------------------------------------

class Relightable:
    """The hooks of a relightable kind, mixed in before its static parent kind (NeuralKind,
    GaussianKind): `static` is the parent's primitives type, `static_variant` its bench model."""

    static: type
    static_variant: str
    conditions = ("light",)

    def at_view(self, prims, camera):
        """The static primitives of the camera's light seen from camera: SH degree 0, the view's colour."""
        return self.static(**{**static_fields(prims, self.static), "sh": view_sh(prims, camera)})

    def at_light(self, prims, light):
        """The static primitives of `light` for every view (SH fitted over directions)."""
        return self.static(**{**static_fields(prims, self.static), "sh": light_sh(prims, light)})

    def at_conditions(self, prims, values):
        return self.at_light(prims, values["light"])

    def check_values(self, prims):
        return super().check_values(prims) or check_network(prims)

    def init_settings(self, config):
        return {**super().init_settings(config), "sh_degree": SH_DEGREE}

    def from_points(self, geometry, settings, seed):
        static = super().from_points(geometry, settings, seed)
        # another stream than the density MLP's (seed + 1): the two networks are not correlated
        network = init_network(len(static), settings.get("color_hidden", DEFAULT_COLOR_HIDDEN), seed + 1)
        return self.primitives(**static_fields(static, self.static), **network)

    def harmonise(self, a, b):
        return harmonise_networks(*super().harmonise(a, b))

    def to_gaussians(self, prims, components=1):
        no_export_without_light(self.name)

    def bench_models(self, scene, generator):
        static = super().bench_models(scene, generator)[self.static_variant]
        return {self.name: self.primitives(**bench_fields(static, self.static, generator))}


def bench_fields(static, static_type: type, generator: torch.Generator) -> dict:
    """bench-train's relightable model: the static bench model at SH degree 0 (as relight runs train)
    with a random colour network (a trained one's cost: its last layer is not zero)."""
    fields_ = {**static_fields(static, static_type), "sh": static.sh[:, :1].clone()}
    network = init_network(len(static), DEFAULT_COLOR_HIDDEN, int(torch.randint(1 << 30, (), generator=generator)))
    network["color_w2"] = 0.1 * torch.randn(network["color_w2"].shape, generator=generator)
    return {**fields_, **network}


# --- neural primitives with a colour network ---------------------------------------------------------

@dataclass
class RelightNeuralPrimitives(NeuralPrimitives):
    """Neural primitives whose colour is (c_dc + c_θ(d, d_l)) · E (eq. 14, module docstring)."""

    color_w1: torch.Tensor = None   # (P, H, 6)
    color_b1: torch.Tensor = None   # (P, H)
    color_w2: torch.Tensor = None   # (P, 3, H)
    color_b2: torch.Tensor = None   # (P, 3)

    kind = "neural-relight"


class RelightNeuralKind(Relightable, NeuralKind):
    name = "neural-relight"
    primitives = RelightNeuralPrimitives
    static, static_variant = NeuralPrimitives, "neural"
    own_params = {**NeuralKind.own_params, **NETWORK}
    lr_keys = {**NeuralKind.lr_keys, **{name: "color" for name in NETWORK}}   # train.lr.color (module docstring)
    # edit/retrain.py's teacher composites the SH colour, which is not this kind's: it refuses it
    retrainable_locally = False
    bench_variants = ("neural-relight",)


# --- Gaussians with a colour network (the baseline) -------------------------------------------------

@dataclass
class RelightGaussians(Gaussians):
    """3D Gaussians whose colour is (c_dc + c_θ(d, d_l)) · E (eq. 14), the network of the neural kind."""

    color_w1: torch.Tensor = None
    color_b1: torch.Tensor = None
    color_w2: torch.Tensor = None
    color_b2: torch.Tensor = None

    kind = "gaussian-relight"


class RelightGaussianKind(Relightable, GaussianKind):
    name = "gaussian-relight"
    primitives = RelightGaussians
    static, static_variant = Gaussians, "gaussian"
    own_params = {**GaussianKind.own_params, **NETWORK}
    lr_keys = {**GaussianKind.lr_keys, **{name: "color" for name in NETWORK}}
    exact_gaussians = False   # only its views under one light are 3D Gaussians with an SH colour
    bench_variants = ("gaussian-relight",)


NEURAL_RELIGHT = register(RelightNeuralKind())
GAUSSIAN_RELIGHT = register(RelightGaussianKind())
