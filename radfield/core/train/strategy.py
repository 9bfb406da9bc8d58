"""Population control: which primitives to clone, split and prune during training.

Strategies behind one small interface (after gsplat's strategy/default.py), so the training
loop knows nothing about the rules; each primitive kind says which one it uses and with which
settings (radfield.core.kinds: PrimitiveKind.strategy, called by `make_strategy`):

    strategy.init_state(num, device) -> {name: tensor (P,)}        accumulators, saved in checkpoints
    strategy.accumulate(state, params, grads, camera, step)         after each view's backward pass
    strategy.refine(state, params, optimizer, step, generator)      after each optimiser step

- `NeuralStrategy` (Splat the Net §3.3, appendix A, and the authors' code): the densification
  signal is the gradient of each primitive's density MLP, ‖∇W1‖ + ‖∇b1‖ + ‖∇W2‖ + |∇b2|, averaged
  over the views in which the primitive was visible. Above `grad_threshold` a primitive is cloned
  (exact copy) when small (max(s) ≤ grow_scale · extent) or split when large (two children drawn
  uniformly inside its bounding ellipsoid, scales / 1.6). A visible primitive whose mean gradient
  stays below `prune_threshold` is pruned, as is one larger than prune_scale · extent, or one whose
  density can never reach the renderer's α threshold. No opacity reset. Both thresholds are
  stated for 64×64 views (REFERENCE_PIXELS) and scaled by √(4096 / pixels per view): the loss is a
  mean over a view's pixels, so the signal of a primitive covering k of N pixels is a mean of k
  per-pixel residual gradients weighted 1/N; at a finer resolution k grows with N and the
  residuals, largely independent, add as √k, so the signal falls as 1/√N. A threshold fixed in
  absolute terms densifies 223×398 photos far less than 64×64 renders (fox_small full size, val:
  28.2 dB with 3k primitives at 1e-3, 30.0 dB with 18k at 1.25e-4, where the default 5e-4 scales
  to 1.07e-4. docs/studies/seeds-radius-sh-viewsize.md).
- `GaussianStrategy` (3DGS adaptive density control): the signal is the screen-space gradient of
  the projected mean, in NDC units as 3DGS (threshold 2e-4). The renderer does not expose the 2D
  means, so it is recovered from the 3D mean's gradient: in camera space ∂u/∂x = fx/z, hence
  ∂L/∂u ≈ (z/fx) ∂L/∂x_cam and ∂L/∂ndc_x = (W/2) ∂L/∂u (likewise for y). This leaves out the part
  of the gradient that reaches the mean through the projected covariance (small next to the
  direct term). Clone/split as above (children sampled from N(0, s²), 3DGS); prune opacity
  < min_opacity, and after the first opacity reset also max(s) > prune_scale · extent; opacities
  are reset to ≤ 0.01 every `opacity_reset_every` steps. 3DGS's screen-size pruning (radius > 20
  px) is left out: the renderer does not report radii, and gsplat disables it by default.
- `FixedPopulation`: no population control (a kind without a densification signal keeps its
  initial primitives).

Budget (`max_primitives`, the paper's memory-budget protocol): growth never exceeds it; when
more primitives qualify than there is room for, those with the largest mean gradient grow. When
the initial population already fills the budget, population control is off altogether (the
paper "omits primitive densification" in its budget experiments).

Parameters are a dict name -> leaf tensor with P rows (see radfield.core.trainer.loop); every change
of rows goes through `edit_rows`, which keeps the Adam moments aligned with the rows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from radfield.core import backends
from radfield.core.geometry.cameras import Camera
from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.core.splat.kernels import ALPHA_MIN
from radfield.util.transfer import to_device

Params = dict[str, torch.Tensor]
MLP_NAMES = ("w1", "b1", "w2", "b2")
SPLIT_CHILDREN = 2
SPLIT_SHRINK = 1.6            # children's scales are the parent's / (0.8 · 2), as 3DGS
GAUSSIAN_RADIUS_SIGMAS = 3.0  # a Gaussian's splat reaches 3σ (the renderer's bound)
RESET_OPACITY = 0.01          # 3DGS opacity reset value
REFERENCE_PIXELS = 64 * 64    # the view size the neural thresholds are stated for


def resolution_factor(pixels: int | None) -> float:
    """The neural thresholds' factor for views of `pixels` pixels (None: 1, as stated): the
    signal falls as 1/√pixels (module docstring)."""
    return 1.0 if pixels is None else math.sqrt(REFERENCE_PIXELS / pixels)


@dataclass(frozen=True)
class Schedule:
    """Refine after each optimiser step that is a multiple of `every` in [start, stop] (steps
    counted from 1); gradients are accumulated until stop."""

    start: int
    stop: int
    every: int

    def accumulating(self, step: int) -> bool:
        return step <= self.stop

    def refining(self, step: int) -> bool:
        return self.start <= step <= self.stop and step % self.every == 0


def refresh_interval(train_cfg: dict) -> int:
    """Steps between refreshes of what the training rules derive from the population's geometry
    (the frequency cap's ρ_max, the view cones of radfield.core.train.positivity, the footprint floor of
    radfield.core.render.antialias): gcd(densify.every, checkpoint_every), so they are refreshed after
    every change of the population and at every step a checkpoint is written at. A killed run
    resumes from a checkpoint and recomputes exactly what the uninterrupted run used; the run
    length plays no part (a 32-step benchmark refreshes as often as a 3000-step run)."""
    return math.gcd(train_cfg["densify"]["every"], train_cfg["checkpoint_every"])


def stale(derived: torch.Tensor | None, count: int, step: int, every: int) -> bool:
    """Whether a per-primitive quantity derived from the geometry (P rows) must be recomputed
    at `step`: never computed, the population changed (not `count` rows), or a refresh step
    (a multiple of `every`, refresh_interval)."""
    return derived is None or derived.shape[0] != count or step % every == 0


class _Strategy:
    """What both strategies share: accumulators, visibility, budgeted growth, row surgery."""

    grad_names: tuple[str, ...] = ()  # parameters whose gradients `accumulate` reads
    # how each accumulator combines over data-parallel ranks (radfield.core.trainer.distributed): sums
    # and counts add (a running maximum, as gsplat's max radii, would need a MAX all-reduce)
    REDUCTIONS = {"grad": "sum", "count": "sum"}
    split_uniform = False             # children inside the ellipsoid (neural) or ~N(0, s²) (3DGS)
    # parameters whose new rows (clones, split children) start from their parent's Adam moments
    # instead of zeros (edit_rows; a kind's own strategy sets it, core/kinds/dynamic.py)
    inherited_moments: tuple[str, ...] = ()
    statistics_op: backends.Op | None = None   # the backend op of a view's statistics (radfield.core.backends)

    def __init__(self, schedule: Schedule, *, extent: float, near: float, grad_threshold: float,
                 grow_scale: float, prune_scale: float, max_primitives: int | None, initial_count: int,
                 attrs: dict | None = None):
        self.schedule = schedule
        self.attrs = attrs or {}   # the kind's attributes (e.g. a dynamic kind's ω), for the kind's own rules
        self.extent = extent
        self.near = near
        self.grad_threshold = grad_threshold
        self.grow_scale = grow_scale
        self.prune_scale = prune_scale
        self.max_primitives = max_primitives
        # a population that starts at the budget is left as it is (paper §4.2)
        self.enabled = max_primitives is None or initial_count < max_primitives
        self._frames = {}   # camera -> its frustum for the fused statistics (_camera_frame)

    def init_state(self, num: int, device) -> dict[str, torch.Tensor]:
        """grad: summed per-view gradient signal; count: views in which the primitive was visible."""
        return {"grad": torch.zeros(num, device=device), "count": torch.zeros(num, device=device)}

    def gathering(self, step: int) -> bool:
        """Whether `accumulate` adds anything during optimiser step `step` (counted from 1)."""
        return self.enabled and self.schedule.accumulating(step)

    @torch.no_grad()
    def accumulate(self, state: dict, params: Params, grads: Params, camera: Camera, step: int) -> None:
        """Add one view's gradient signal (grads: that view's gradients of `grad_names`) during
        optimiser step `step` (counted from 1)."""
        if not self.gathering(step):
            return
        op = _statistics_kernel(self.statistics_op, state, params, grads)
        if op is not None:   # one backend pass (fused: core/backends/csrc/strategy_kernels.cpp)
            self._accumulate_op(op, state, params, grads, camera)
            return
        visible = in_frustum(params["means"], self._radius(params), camera, self.near)
        state["grad"] += torch.where(visible, self._signal(params, grads, camera), 0.0)
        state["count"] += visible

    def _camera_frame(self, camera: Camera, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(w2c rows (3, 4), side_normals (4, 3)) of a camera in like's dtype and device, for the
        fused statistics: kept per camera object (a training view comes back every epoch, and its
        4×4 inverse and normals cost more than the op itself)."""
        key = (id(camera), like.dtype, like.device)
        frame = self._frames.get(key)
        if frame is None or frame[0] is not camera:   # `is`: an id can be reused by a new camera
            if len(self._frames) >= 4096:   # jittered views are new cameras every step: stay bounded
                self._frames.clear()
            frame = self._frames[key] = (camera, to_device(camera.w2c[:3], like.device, like.dtype).contiguous(),
                                         side_normals(camera, like))
        return frame[1], frame[2]

    def _grow_and_prune(self, state: dict, params: Params, optimizer, prune: torch.Tensor,
                        generator: torch.Generator) -> dict[str, int]:
        """Clone or split the primitives whose mean signal exceeds the threshold (within the
        budget), drop `prune`, reset the accumulators."""
        seen = state["count"] > 0
        mean = state["grad"] / state["count"].clamp_min(1)
        if bool(prune.all()):
            prune = torch.zeros_like(prune)  # never empty the scene: nothing would be left to train
        grow = seen & (mean > self.grad_threshold) & ~prune
        if self.max_primitives is not None:
            room = max(self.max_primitives - int((~prune).sum()), 0)  # each growth adds one net primitive
            if int(grow.sum()) > room:
                ranked = torch.where(grow, mean, -math.inf)
                grow = torch.zeros_like(grow)
                grow[torch.topk(ranked, room).indices] = True
        split = grow & (self._max_scale(params) > self.grow_scale * self.extent)
        clone = grow & ~split
        new_rows = {name: torch.cat([rows[clone], rows[split].repeat(SPLIT_CHILDREN, *[1] * (rows.ndim - 1))])
                    for name, rows in ((n, p.detach()) for n, p in params.items())}
        children = self._children(params, split, generator)
        n_clone = int(clone.sum())
        for name, value in children.items():
            new_rows[name][n_clone:] = value
        parents = None
        if self.inherited_moments:   # the new rows' parents, in new_rows' order
            parents = torch.cat([clone.nonzero()[:, 0], split.nonzero()[:, 0].repeat(SPLIT_CHILDREN)])
        edit_rows(params, optimizer, ~prune & ~split, new_rows, parents, self.inherited_moments)
        state.update(self.init_state(params["means"].shape[0], params["means"].device))
        return {"cloned": n_clone, "split": int(split.sum()), "pruned": int(prune.sum())}

    def _children(self, params: Params, split: torch.Tensor, generator: torch.Generator) -> Params:
        """Means and log-scales of SPLIT_CHILDREN children per split primitive, child-major."""
        means, log_scales = params["means"].detach()[split], params["log_scales"].detach()[split]
        n = means.shape[0] * SPLIT_CHILDREN
        if self.split_uniform:  # uniform in the unit ball, then into the ellipsoid B(μ, R, s)
            direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=generator), dim=-1)
            offsets = direction * torch.rand(n, 1, generator=generator) ** (1 / 3)
        else:
            offsets = torch.randn(n, 3, generator=generator)
        offsets = offsets.to(means) * torch.exp(log_scales).repeat(SPLIT_CHILDREN, 1)
        rot = quat_to_rotmat(params["quats"].detach()[split]).repeat(SPLIT_CHILDREN, 1, 1)
        return {"means": means.repeat(SPLIT_CHILDREN, 1) + (rot @ offsets[:, :, None])[:, :, 0],
                "log_scales": log_scales.repeat(SPLIT_CHILDREN, 1) - math.log(SPLIT_SHRINK)}

    def _max_scale(self, params: Params) -> torch.Tensor:
        return torch.exp(params["log_scales"].detach().amax(-1))

    def _radius(self, params: Params) -> torch.Tensor:
        return self._max_scale(params)


class NeuralStrategy(_Strategy):
    """Splat the Net's MLP-gradient densification (see the module docstring)."""

    grad_names = MLP_NAMES
    split_uniform = True
    statistics_op = backends.Op.NEURAL_ACCUMULATE

    def __init__(self, schedule: Schedule, *, prune_threshold: float, **kwargs):
        super().__init__(schedule, **kwargs)
        self.prune_threshold = prune_threshold

    def _accumulate_op(self, op, state: dict, params: Params, grads: Params, camera: Camera) -> None:
        means = params["means"]
        op(state["grad"], state["count"], means, params["log_scales"],
           *(grads[n] for n in MLP_NAMES), *self._camera_frame(camera, means), 1.0, self.near)

    def _signal(self, params: Params, grads: Params, camera: Camera) -> torch.Tensor:
        # the authors' statistic: the sum of the per-tensor gradient norms of the MLP
        return (grads["w1"].flatten(1).norm(dim=-1) + grads["b1"].norm(dim=-1)
                + grads["w2"].norm(dim=-1) + grads["b2"].abs())

    @torch.no_grad()
    def refine(self, state: dict, params: Params, optimizer, step: int, generator: torch.Generator) -> dict[str, int]:
        if not (self.enabled and self.schedule.refining(step)):
            return {}
        mean = state["grad"] / state["count"].clamp_min(1)
        prune = ((state["count"] > 0) & (mean < self.prune_threshold)) \
            | (self._max_scale(params) > self.prune_scale * self.extent) \
            | negligible_density(params["w2"].detach(), params["b2"].detach())
        return self._grow_and_prune(state, params, optimizer, prune, generator)


class GaussianStrategy(_Strategy):
    """3DGS adaptive density control (see the module docstring)."""

    grad_names = ("means",)
    statistics_op = backends.Op.GAUSSIAN_ACCUMULATE

    def __init__(self, schedule: Schedule, *, min_opacity: float, opacity_reset_every: int, **kwargs):
        super().__init__(schedule, **kwargs)
        self.min_opacity = min_opacity
        self.opacity_reset_every = opacity_reset_every

    def _radius(self, params: Params) -> torch.Tensor:
        return GAUSSIAN_RADIUS_SIGMAS * self._max_scale(params)

    def opacity_logits(self, params: Params) -> torch.Tensor:
        """The opacity logits (P,) that pruning compares with min_opacity (a time-conditioned kind:
        their bound over time, core/kinds/dynamic.py)."""
        return params["opacities"].detach()

    def reset_opacities(self, params: Params, ceiling: float) -> None:
        """3DGS's opacity reset: every opacity_logits at most `ceiling`, in place."""
        params["opacities"].clamp_(max=ceiling)

    def _accumulate_op(self, op, state: dict, params: Params, grads: Params, camera: Camera) -> None:
        means = params["means"]
        op(state["grad"], state["count"], means, params["log_scales"], grads["means"],
           *self._camera_frame(camera, means), GAUSSIAN_RADIUS_SIGMAS, self.near, camera.fx,
           camera.fy, camera.width, camera.height)

    def _signal(self, params: Params, grads: Params, camera: Camera) -> torch.Tensor:
        w2c = to_device(camera.w2c, params["means"].device, params["means"].dtype)
        depth = params["means"].detach() @ w2c[2, :3] + w2c[2, 3]
        grad_cam = grads["means"] @ w2c[:3, :3].T
        ndc_x = grad_cam[:, 0] * depth / camera.fx * (camera.width / 2)
        ndc_y = grad_cam[:, 1] * depth / camera.fy * (camera.height / 2)
        return torch.hypot(ndc_x, ndc_y)

    @torch.no_grad()
    def refine(self, state: dict, params: Params, optimizer, step: int, generator: torch.Generator) -> dict[str, int]:
        if not (self.enabled and self.schedule.accumulating(step)):
            return {}
        report = {}
        if self.schedule.refining(step):
            prune = torch.sigmoid(self.opacity_logits(params)) < self.min_opacity
            if step > self.opacity_reset_every:
                prune |= self._max_scale(params) > self.prune_scale * self.extent
            report = self._grow_and_prune(state, params, optimizer, prune, generator)
        if step % self.opacity_reset_every == 0:
            ceiling = math.log(RESET_OPACITY / (1 - RESET_OPACITY))
            self.reset_opacities(params, ceiling)
            reset_moments(optimizer, "opacities")
            report["opacity_reset"] = 1
        return report


class FixedPopulation:
    """No population control: nothing is accumulated, nothing grows or is pruned."""

    grad_names: tuple[str, ...] = ()
    REDUCTIONS: dict[str, str] = {}

    def init_state(self, num: int, device) -> dict[str, torch.Tensor]:
        return {}

    def gathering(self, step: int) -> bool:
        return False

    def accumulate(self, state: dict, params: Params, grads: Params, camera: Camera, step: int) -> None:
        return None

    def refine(self, state: dict, params: Params, optimizer, step: int, generator: torch.Generator) -> dict[str, int]:
        return {}


# --- geometry tests --------------------------------------------------------------------------

def in_frustum(means: torch.Tensor, radius: torch.Tensor, camera: Camera, near: float) -> torch.Tensor:
    """Whether the sphere of `radius` (P,) around each mean (P, 3) meets the camera's view
    frustum (beyond the near plane, inside the four side planes). Conservative: a sphere that
    only touches a frustum corner region counts as visible."""
    w2c = to_device(camera.w2c, means.device, means.dtype)
    p = means.detach() @ w2c[:3, :3].T + w2c[:3, 3]
    inside = (p @ side_normals(camera, means).T).amin(-1) >= -radius   # all four planes: the nearest one
    return inside & (p[:, 2] + radius > near)


def side_normals(camera: Camera, like: torch.Tensor) -> torch.Tensor:
    """The unit inward normals (4, 3) of the side planes of the view frustum, in camera space,
    through the camera centre: u ≥ 0, u ≤ W, v ≥ 0, v ≤ H (dtype and device of `like`)."""
    normals = torch.tensor([[camera.fx, 0.0, camera.cx], [-camera.fx, 0.0, camera.width - camera.cx],
                            [0.0, camera.fy, camera.cy], [0.0, -camera.fy, camera.height - camera.cy]])
    normals = to_device(normals, like.device, like.dtype)
    return torch.nn.functional.normalize(normals, dim=-1)


def _statistics_kernel(op: backends.Op | None, state: dict, params: Params, grads: Params):
    """The backend implementation of a view's statistics (radfield.core.backends: `op`) when one
    runs the means' device and dtype and every tensor shares them; None: the torch twin of `accumulate`."""
    if op is None:
        return None
    means = params["means"]
    kernel = backends.kernel(op, means.device, means.dtype)
    tensors = (state["grad"], state["count"], params["log_scales"], *grads.values())
    if kernel is not None and all(t is not None and t.device == means.device and t.dtype == means.dtype
                                  for t in tensors):
        return kernel
    return None


def negligible_density(w2: torch.Tensor, b2: torch.Tensor) -> torch.Tensor:
    """Neural primitives (P,) that can never reach the renderer's α threshold: σ ≤ ‖W2‖₁ + b2
    everywhere (paper eq. 6) and a chord is at most 2 in units of max(s), so I ≤ 2 max(0, ‖W2‖₁ + b2).
    Windowed too: along any chord (1/max s) ∫ 1.5 (1 − r²) dℓ ≤ 2, its value on the longest axis."""
    return 2.0 * (w2.abs().sum(-1) + b2) < -math.log1p(-ALPHA_MIN)


# --- optimiser-state surgery -----------------------------------------------------------------

def edit_rows(params: Params, optimizer: torch.optim.Optimizer, keep: torch.Tensor, new_rows: Params,
              parents: torch.Tensor | None = None, inherited: tuple[str, ...] = ()) -> None:
    """Replace every parameter by cat(param[keep], new_rows[name]) as a fresh leaf tensor, with
    its Adam moments edited alike (kept rows keep theirs, new rows start at zero, or, for the
    parameters named in `inherited`, at the moments of their rows `parents` (index per new row)).
    Needs one parameter per optimiser group, with the group's "name" a key of params."""
    for group in optimizer.param_groups:
        name = group["name"]
        old = group["params"][0]
        new = torch.cat([old.detach()[keep], new_rows[name].to(old)]).requires_grad_(old.requires_grad)
        state = optimizer.state.pop(old, None)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                added = state[key][parents] if name in inherited else torch.zeros_like(new_rows[name], dtype=state[key].dtype)
                state[key] = torch.cat([state[key][keep], added])
            optimizer.state[new] = state
        group["params"][0] = new
        params[name] = new


def reset_moments(optimizer: torch.optim.Optimizer, name: str) -> None:
    """Zero the Adam moments of one parameter group (after its values were reset)."""
    for group in optimizer.param_groups:
        if group["name"] == name:
            state = optimizer.state.get(group["params"][0])
            for key in ("exp_avg", "exp_avg_sq"):
                if state and key in state:
                    state[key].zero_()
