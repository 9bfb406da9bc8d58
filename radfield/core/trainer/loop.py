"""The optimisation loop: primitives, cameras, images and the `train` config section in, trained
primitives out. A pure library: no pipeline, no files except through the checkpoint helpers.

Per step (3DGS's recipe with Splat the Net's regulariser, §3.3 and appendix A):
    loss = (1 − λ) L1 + λ D-SSIM + λ_aniso · mean std(s / min(s))
           [+ λ_w1 · mean ‖W1‖²_F + λ_density · mean (‖W2‖₁ + |b2|), neural primitives]
over `batch_views` training views (each view's photometric loss weighted 1/batch_views); Adam
with one group per parameter tensor (means' rate × scene extent, decaying exponentially to
`means_lr_final_ratio` of it at the last step); the active SH degree rises by one every
`sh_increase_every` steps; population control by radfield.core.train.strategy after the step, then
(neural) the frequency cap of radfield.core.train.frequency (`frequency_cap`) projects W1's rows,
with `nonnegative_density` radfield.core.train.positivity projects (W2, b2) so that σ ≥ 0 everywhere
in the primitives whose training views lie in a narrow cone, and the footprint floor of
radfield.core.render.antialias (`min_footprint`) raises scales below k pixels.
With `ray_jitter` every training view is rendered with its principal point moved by a random
sub-pixel offset (radfield.core.render.antialias): the pixels' rays sample their whole area over the run.

Views with a valid-pixel mask (undistorted photos) are measured on their valid pixels only (the
loss and the per-step PSNR, radfield.core.train.losses). With `random_background` and RGBA training
views (`alphas`), every view of a step is composited on a fresh uniformly random colour, and
rendered over it: a transparent pixel then has no fixed colour to be fitted by floaters. Every
`eval_every` steps and at the last, `held_out(primitives)` (e.g. the PSNR of held-out views) is
reported as info["test_psnr"]: for information only, it changes nothing in training.

Continuing: a start_state of a finished run (its step s < the new cfg["iterations"] N) goes on
from step s with its parameters, Adam moments and strategy accumulators, under the schedules of
an N-step run: the means' rate is lr0 · r^(t / (N − 1)) at step t (so at step s it is back up to
lr0 · r^(s / (N − 1)) and decays to lr0 · r at step N − 1), the SH degree and densification
follow their step thresholds as in an N-step run. It is not the same as a fresh N-step run.

Host reads: the loop reads nothing from the device on most steps (on a GPU a read waits for every
queued kernel). A step's loss and PSNR stay on the device (StepRecords) until the records are read
together every `log_every` steps and at the steps that read the device anyway (refinement, held-out
views, checkpoints, the last step); the per-step randomness is drawn on the CPU and copied over
without waiting.

Randomness (view order, split children, ray jitter) is drawn from generators seeded by (seed, step), so a
run is a pure function of its inputs and the step count: a checkpoint holds parameters, Adam
moments, strategy accumulators and the step, and resuming from it reproduces the uninterrupted
run bit for bit on the CPU. Checkpoints are safetensors files with a JSON header, never pickles.

Data parallel (`world`, radfield.core.trainer.distributed.StepSync): each rank renders its share of the
step's views, one all-reduce sums the gradients and the strategy's per-step increments, and every
rank applies the same step; with one rank the hooks are the identity.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from radfield.core import kinds
from radfield.core.train.coarse_to_fine import ViewPyramid, factor_at
from radfield.core.train.footprint import FootprintFloor
from radfield.core.render.antialias import jitter_offsets, render_supersampled, shifted
from radfield.util.atomic import atomic_write
from radfield.core.geometry.cameras import Camera
from radfield.core.trainer.distributed import StepSync, World
from radfield.errors import RadfieldError
from radfield.core.train.losses import anisotropy, photometric, psnr
from radfield.core.train.strategy import Schedule
from radfield.core.splat.sh import join_sh, num_sh_coeffs

CHECKPOINT_FORMAT = "radfield-checkpoint"
CHECKPOINT_VERSION = 1
ADAM_EPS = 1e-15  # as 3DGS: the moments of tiny gradients (SH rest, MLP) still move the parameters

_VIEWS, _REFINE, _BACKGROUND, _JITTER = 0, 1, 2, 3  # random streams


@dataclass
class TrainState:
    """A snapshot of training after `step` optimiser steps.

    kind: the primitive kind (radfield.core.kinds); attrs: its non-tensor attributes (neural: ω0
    and the density window), which checkpoints carry in their header.
    params: {name: (P, ...) tensor}, the kind's parameter names (kinds.get(kind).param_names());
    SH is split into sh_dc (P, 1, 3) and sh_rest (P, K−1, 3) because they learn at different rates.
    moments: {name: {"exp_avg", "exp_avg_sq", "step"}}, Adam's state per parameter.
    strategy: the population-control accumulators {name: (P,)}.
    """

    step: int
    kind: str
    attrs: dict
    params: dict[str, torch.Tensor]
    moments: dict[str, dict[str, torch.Tensor]]
    strategy: dict[str, torch.Tensor]

    def primitives(self) -> kinds.Primitives:
        """The trained primitives (detached), SH bands merged back."""
        return assemble(self.params, self.kind, self.attrs).map(lambda t: t.detach().clone())


def make_strategy(kind: str, densify: dict, *, extent: float, near: float, max_primitives: int | None,
                  initial_count: int, pixels: int | None = None, attrs: dict | None = None):
    """The strategy of primitive `kind` (radfield.core.kinds: its `strategy` hook) from the
    train.densify config; `pixels`: a training view's pixel count, which scales the neural
    thresholds (resolution_factor; None leaves them as configured). 3DGS's NDC-gradient threshold
    needs no scaling. `attrs`: the kind's attributes (TrainState.attrs; None: the kind's defaults),
    which a kind's own rules may read (the dynamic Gaussians' ω, core/kinds/dynamic.py)."""
    schedule = Schedule(densify["start"], densify["stop"], densify["every"])
    attrs = kinds.get(kind).default_attrs() if attrs is None else attrs
    return kinds.get(kind).strategy(densify, schedule, pixels=pixels, extent=extent, near=near,
                                    grow_scale=densify["grow_scale"], max_primitives=max_primitives,
                                    initial_count=initial_count, attrs=attrs)

def train(prims: kinds.Primitives, train_cameras: Sequence[Camera], train_images: torch.Tensor,
          cfg: dict, *, background: Sequence[float], extent: float, seed: int, device: str | torch.device = "cpu",
          near: float = 0.01, max_pairs: int = 1 << 20, start_state: TrainState | None = None,
          masks: torch.Tensor | None = None, alphas: torch.Tensor | None = None,
          on_step: Callable[[int, dict], None] | None = None,
          held_out: Callable[[kinds.Primitives], float] | None = None,
          checkpoint: Callable[[TrainState], None] | None = None, world: World | None = None) -> TrainState:
    """Optimise `prims` against the views for cfg["iterations"] steps; returns the final state
    (`.primitives()` is the trained model).

    prims: the initial primitives (also when resuming: population control needs their count).
    train_images: (N, H, W, 3) float in [0, 1], matching train_cameras.
    masks: (N, H, W) bool valid pixels of each image, or None (all valid).
    alphas: (N, H, W) alpha of RGBA images (train_images are composited on `background`), or
    None; with cfg["random_background"] they are recomposited on a random colour every step.
    cfg: the `train` config section (pipeline.yaml documents every key), and "supersample" (optional,
    default 1): render.supersample, each training view rendered with n × n rays per pixel.
    extent: scene radius (3DGS's camera extent), in the frame of prims and cameras.
    start_state: resume from this snapshot (e.g. load_checkpoint) instead of from prims.
    on_step(step, info): once for every step, in order; info has loss, psnr (of this step's views),
    primitives and what population control did (and test_psnr on the steps held_out was measured).
    The calls come in bursts when the device is read (StepRecords): every cfg["log_every"] steps
    (log_interval: by default every step on the CPU, every LOG_EVERY_GPU on a GPU) and at every
    refinement, held-out, checkpoint and last step; a caller that clocks single steps sets it to 1.
    held_out(primitives): measured every cfg["eval_every"] steps (0: never) and at the last step.
    checkpoint(state): every cfg["checkpoint_every"] steps before the last.
    world: the ranks of a data-parallel training (radfield.core.trainer.distributed; None: this process
    alone). Each rank then renders its share of the step's views and the gradients are summed
    over the ranks before the Adam step, so every rank holds the same model (radfield.core.trainer.dataparallel).
    """
    if len(train_cameras) != len(train_images) or not len(train_cameras):
        raise ValueError(f"training needs one image per camera, got {len(train_cameras)} cameras "
                         f"and {len(train_images)} images")
    max_primitives = cfg["max_primitives"]
    if max_primitives is not None and len(prims) > max_primitives:
        raise ValueError(f"{len(prims)} initial primitives exceed train.max_primitives={max_primitives}")
    device = torch.device(device)
    images = train_images.to(device=device, dtype=torch.float32)
    masks = None if masks is None else masks.to(device=device, dtype=torch.bool)
    alphas = None if alphas is None or not cfg["random_background"] else alphas.to(device=device,
                                                                                  dtype=torch.float32)
    state = start_state or initial_state(prims, cfg["sh_degree"])
    kind = kinds.get(state.kind)
    params = {name: state.params[name].detach().to(device).clone().requires_grad_(True)
              for name in kind.param_names()}
    optimizer = make_optimizer(params, cfg["lr"], extent, state.kind)
    _load_moments(optimizer, state.moments, device)
    strategy = make_strategy(state.kind, cfg["densify"], extent=extent, near=near, max_primitives=max_primitives,
                             initial_count=len(prims), pixels=images.shape[1] * images.shape[2], attrs=state.attrs)
    accumulators = {k: v.to(device) for k, v in state.strategy.items()} or strategy.init_state(len(prims), device)
    bg = torch.as_tensor(background, dtype=torch.float32, device=device)
    iterations, batch = cfg["iterations"], cfg["batch_views"]
    records = StepRecords(on_step, batch, log_interval(cfg, device))
    zero = torch.zeros((), dtype=torch.float64, device=device)   # the start of a step's device sums
    supersample = cfg.get("supersample", 1)  # render.supersample, put into cfg by the train stage
    means_lr = cfg["lr"]["means"] * extent
    sync = StepSync(world, strategy.REDUCTIONS)  # the identity with one rank
    sync.check(params, state.step, first=True)
    # the kind's projections after every step (neural: the frequency cap, σ ≥ 0), then the
    # footprint floor of every kind (anti-aliasing, core/render/antialias.py)
    rules = [*kind.training_rules(train_cameras, cfg, state.attrs, near),
             FootprintFloor.for_training(train_cameras, cfg, near=near)]
    for rule in rules:
        rule.apply(params, state.step)
    # coarse to fine (train.coarse_levels): the views at the step's downscale factor
    pyramid = ViewPyramid(train_cameras, images, masks, alphas)

    for step in range(state.step, iterations):
        factor = factor_at(step, iterations, cfg["coarse_levels"], cfg["coarse_until"])
        cameras, targets, valid, coverage = pyramid.at(factor)
        optimizer.param_groups[0]["lr"] = decayed(means_lr, cfg["means_lr_final_ratio"], step, iterations)
        degree = min(cfg["sh_degree"], step // cfg["sh_increase_every"])
        regulariser = regularisers(params, cfg, state.kind) if sync.rank == 0 else None  # counted once over the ranks
        if regulariser is not None:
            regulariser.backward()
        loss_sum = psnr_sum = zero
        backgrounds = None if alphas is None else torch.rand(batch, 3, generator=generator(seed, _BACKGROUND, step))
        if backgrounds is not None:   # drawn on the CPU; a blocking copy would wait for the device's queue
            backgrounds = backgrounds.to(device, non_blocking=True)
        offsets = jitter_offsets(cfg["ray_jitter"], batch, generator(seed, _JITTER, step))
        gathering = strategy.gathering(step + 1)
        gathered = sync.gather_into(accumulators, gathering)
        tracked = strategy.grad_names if gathering else ()   # accumulate reads nothing otherwise
        # k: the view's place in the whole batch (its random background), the same on every rank
        for k, view in sync.share(list(enumerate(views_for_step(seed, step, batch, len(train_cameras))))):
            before = {n: None if params[n].grad is None else params[n].grad.clone() for n in tracked}
            view_bg, target = bg, targets[view]
            if backgrounds is not None:  # the same RGBA pixels "over" another colour
                view_bg = backgrounds[k]
                target = target + (1.0 - coverage[view])[..., None] * (view_bg - bg)
            camera = shifted(cameras[view], offsets[k])  # sub-pixel ray jitter (train.ray_jitter)
            out = render_supersampled(assemble(params, state.kind, state.attrs), camera, supersample,
                                      background=view_bg, near=near, sh_degree=degree, max_pairs=max_pairs)
            mask = None if valid is None else valid[view]
            loss = photometric(out.color, target, cfg["lambda_dssim"], mask)
            (loss / batch).backward()
            # this view's own gradients (unscaled), what the densification statistics measure (of a
            # full-size view: a view at 1/f of the side carries f times the signal, coarse_to_fine.py)
            grads = {n: own_gradient(params[n].grad, before[n], batch) for n in tracked}
            if factor > 1:
                grads = {n: g / factor for n, g in grads.items()}
            strategy.accumulate(gathered, params, grads, camera, step + 1)
            # float64 sums on the device, added in the order Python added the floats: the same bits
            loss_sum = loss_sum + loss.detach().double()
            psnr_sum = psnr_sum + psnr(out.color.detach().clamp(0, 1), target, mask).double()
        loss_sum, psnr_sum = sync.reduce(params, accumulators, loss_sum, psnr_sum, step + 1)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        refined = strategy.refine(accumulators, params, optimizer, step + 1, generator(seed, _REFINE, step))
        for rule in rules:
            rule.apply(params, step + 1)
        sync.check(params, step + 1)
        info = {"primitives": params["means"].shape[0], **refined}   # host values: no read of the device
        every = cfg["eval_every"]
        if held_out is not None and ((every and (step + 1) % every == 0) or step + 1 == iterations):
            with torch.no_grad():
                info["test_psnr"] = float(held_out(assemble(params, state.kind, state.attrs).map(torch.Tensor.detach)))
        saving = checkpoint is not None and (step + 1) % cfg["checkpoint_every"] == 0 and step + 1 < iterations
        records.add(step + 1, loss_sum, psnr_sum, info)
        # steps that read the device anyway (refinement, held-out views, checkpoint) read the records
        # too; a checkpoint's step is in the log before the checkpoint is (resume truncates the log there)
        if (step + 1) % records.every == 0 or refined or "test_psnr" in info or saving or step + 1 == iterations:
            records.flush()
        if saving:
            checkpoint(snapshot(step + 1, state, params, optimizer, accumulators))
    return snapshot(max(iterations, state.step), state, params, optimizer, accumulators)


LOG_EVERY_GPU = 50   # train.log_every's default off the CPU (log_interval)


def log_interval(cfg: dict, device: torch.device) -> int:
    """Steps between reads of the step statistics: train.log_every, or by default (null) 1 on the
    CPU, where reading a tensor waits for nothing, and LOG_EVERY_GPU on a GPU, where every read
    drains the device's queue and leaves it idle while the host launches the next step's kernels
    (50 steps: about a second of training at the GPU path's ~20 ms a step, a progress bar that
    still moves every second, and at most 50 records lost to a kill, which resume recomputes)."""
    every = cfg.get("log_every")
    if every is None:
        return 1 if device.type == "cpu" else LOG_EVERY_GPU
    if every < 1:
        raise ValueError(f"train.log_every must be at least 1, got {every}")
    return every


class StepRecords:
    """The statistics of the steps since the last read, kept on the device: each step's loss and
    PSNR sums over its views (float64 tensors) and its host values (primitives, population control,
    test_psnr). `flush` reads all the sums with one stack(...).tolist() and calls on_step(step, info)
    for every pending step, in order, with info's loss and psnr the batch means as floats. So
    on_step sees every step, late by up to `every` steps, with the values it saw when it was
    called after each step."""

    def __init__(self, on_step: Callable[[int, dict], None] | None, batch: int, every: int):
        self.on_step, self.batch, self.every = on_step, batch, every
        self.pending: list[tuple[int, torch.Tensor, torch.Tensor, dict]] = []

    def add(self, step: int, loss_sum: torch.Tensor, psnr_sum: torch.Tensor, info: dict) -> None:
        if self.on_step is not None:   # nobody reads them: keep nothing
            self.pending.append((step, loss_sum, psnr_sum, info))

    def flush(self) -> None:
        if not self.pending:
            return
        pending, self.pending = self.pending, []
        sums = torch.stack([t for _, loss_sum, psnr_sum, _ in pending for t in (loss_sum, psnr_sum)]).tolist()
        for k, (step, _, _, info) in enumerate(pending):
            self.on_step(step, {"loss": sums[2 * k] / self.batch, "psnr": sums[2 * k + 1] / self.batch, **info})


def own_gradient(total: torch.Tensor, before: torch.Tensor | None, batch: int) -> torch.Tensor:
    """One view's gradient, unscaled, from the accumulated `total` and the `before` it (None: no
    gradient yet): (total − before) · batch. Without an earlier gradient and with one view a step
    that is `total` itself, returned without the two copies (the same values, bit for bit)."""
    own = total if before is None else total - before
    return own if batch == 1 else own * batch


def regularisers(params: dict[str, torch.Tensor], cfg: dict, kind: str) -> torch.Tensor | None:
    """The weighted geometry and density regularisers of a step (None when all are off): the
    anisotropy of the scales, then the kind's own terms (neural: the frequency (‖W1‖²) and density
    (‖W2‖₁ + |b2|) magnitudes of radfield.core.train.losses)."""
    terms = []
    if cfg["lambda_aniso"] > 0:
        terms.append(cfg["lambda_aniso"] * anisotropy(params["log_scales"]))
    terms += kinds.get(kind).regularisers(params, cfg)
    return sum(terms) if terms else None


# --- parameters and optimiser ----------------------------------------------------------------

def initial_state(prims: kinds.Primitives, sh_degree: int) -> TrainState:
    """Step 0: the parameters of prims, SH padded with zeros (or cut) to `sh_degree`."""
    kind = kinds.of(prims)
    k = num_sh_coeffs(sh_degree)
    sh = prims.sh[:, :k]
    sh = torch.cat([sh, sh.new_zeros(len(prims), k - sh.shape[1], 3)], 1)
    tensors = prims.tensors()
    params = {name: sh[:, :1] if name == "sh_dc" else sh[:, 1:] if name == "sh_rest" else tensors[name]
              for name in kind.param_names()}
    return TrainState(0, kind.name, kind.attrs(prims), {n: t.detach().clone() for n, t in params.items()}, {}, {})


def assemble(params: dict[str, torch.Tensor], kind: str, attrs: dict) -> kinds.Primitives:
    """Primitives of `kind` built from the parameter tensors and the kind's attributes
    (differentiable: no copies)."""
    tensors = {n: t for n, t in params.items() if n not in ("sh_dc", "sh_rest")}
    sh = join_sh(params["sh_dc"], params["sh_rest"])   # the fused renderer reads the two parts (core/splat/sh.py)
    return kinds.get(kind).assemble(tensors, attrs, sh=sh)


def make_optimizer(params: dict[str, torch.Tensor], lr: dict, extent: float, kind: str) -> torch.optim.Adam:
    """Adam with one named group per parameter, in the order of `params` (means first: the loop
    schedules the rate of group 0); each group's rate is the train.lr key the kind names for it."""
    lr_key = kinds.get(kind).lr_key
    groups = [{"params": [t], "name": n, "lr": lr[lr_key(n)] * (extent if n == "means" else 1.0)}
              for n, t in params.items()]
    # fused Adam: one pass per tensor instead of ~10 ops (on the CPU 5 ms → 1.5 ms a step at 10k
    # primitives; on a GPU one launch per tensor instead of ~10)
    fused = any(all(t.device.type == where for t in params.values()) for where in ("cpu", "cuda"))
    return torch.optim.Adam(groups, eps=ADAM_EPS, fused=fused or None)


def decayed(lr: float, final_ratio: float, step: int, iterations: int) -> float:
    """Exponential decay from lr at step 0 to lr · final_ratio at the last step (3DGS's means schedule)."""
    t = min(step / max(iterations - 1, 1), 1.0)
    return lr * final_ratio**t


def generator(seed: int, stream: int, index: int) -> torch.Generator:
    """An independent CPU generator for (seed, stream, index): randomness as a function of the step."""
    entropy = np.random.SeedSequence([seed, stream, index]).generate_state(2, dtype=np.uint32)
    return torch.Generator().manual_seed(int(entropy[0]) << 32 | int(entropy[1]))


def views_for_step(seed: int, step: int, batch: int, num_views: int) -> list[int]:
    """The training views of a step: the views are walked in a fresh random order every epoch
    (as 3DGS's viewpoint stack); the batch of step s covers positions s·batch ... s·batch + batch − 1."""
    out = []
    for k in range(step * batch, step * batch + batch):
        epoch, position = divmod(k, num_views)
        out.append(int(torch.randperm(num_views, generator=generator(seed, _VIEWS, epoch))[position]))
    return out


def snapshot(step: int, state: TrainState, params: dict, optimizer: torch.optim.Adam, accumulators: dict) -> TrainState:
    """The live training objects as a TrainState (shares tensors; save or clone it before training goes on)."""
    moments = {}
    for group in optimizer.param_groups:
        adam = optimizer.state.get(group["params"][0])
        if adam:
            moments[group["name"]] = {k: adam[k] for k in ("exp_avg", "exp_avg_sq", "step")}
    return TrainState(step, state.kind, state.attrs, {n: p.detach() for n, p in params.items()}, moments,
                      dict(accumulators))


def _load_moments(optimizer: torch.optim.Adam, moments: dict, device) -> None:
    for group in optimizer.param_groups:
        if group["name"] in moments:
            saved = moments[group["name"]]
            # Adam keeps its step count on the CPU, fused Adam on a GPU on the GPU
            counted_on = device if group.get("fused") and torch.device(device).type == "cuda" else "cpu"
            optimizer.state[group["params"][0]] = {
                "step": saved["step"].detach().clone().to(counted_on),
                "exp_avg": saved["exp_avg"].detach().to(device).clone(),
                "exp_avg_sq": saved["exp_avg_sq"].detach().to(device).clone(),
            }


# --- checkpoints -----------------------------------------------------------------------------

def save_checkpoint(path: str | Path, state: TrainState, note: dict | None = None) -> None:
    """Write a TrainState atomically as one safetensors file: tensors param.NAME, adam.NAME.KEY,
    strategy.NAME; metadata key "radfield-checkpoint" holds JSON {format, version, step, kind, note}
    and the kind's attributes (neural: omega0, window) (`note`: the caller's own JSON, e.g. what the
    state is valid for)."""
    path = Path(path)
    tensors = {k: t.detach().cpu().contiguous() for k, t in state_tensors(state).items()}
    # one metadata key: safetensors writes several in a random order, and equal states should
    # give equal bytes
    header = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "step": state.step, "kind": state.kind,
              **state.attrs, "note": note}
    meta = {CHECKPOINT_FORMAT: json.dumps(header, sort_keys=True)}
    atomic_write(path, lambda tmp: save_file(tensors, str(tmp), metadata=meta))


def checkpoint_header(path: str | Path) -> dict:
    """The JSON header of a checkpoint (step, kind, the kind's attributes, note) without reading its tensors."""
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            header = json.loads((f.metadata() or {}).get(CHECKPOINT_FORMAT, "{}"))
    except (OSError, ValueError, SafetensorError) as error:
        raise RadfieldError(f"{path}: unreadable checkpoint ({error}); remove it to start over") from None
    if header.get("format") != CHECKPOINT_FORMAT or header.get("version") != CHECKPOINT_VERSION:
        raise RadfieldError(f"{path}: not a version {CHECKPOINT_VERSION} radfield checkpoint")
    return header


def load_checkpoint(path: str | Path) -> TrainState:
    """Read a checkpoint written by save_checkpoint (tensors on the CPU)."""
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            header = json.loads((f.metadata() or {}).get(CHECKPOINT_FORMAT, "{}"))
            if header.get("format") != CHECKPOINT_FORMAT or header.get("version") != CHECKPOINT_VERSION:
                raise RadfieldError(f"{path}: not a version {CHECKPOINT_VERSION} radfield checkpoint")
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except (OSError, ValueError, KeyError, SafetensorError) as error:
        raise RadfieldError(f"{path}: unreadable checkpoint ({error}); remove it to start over") from None
    return state_from_tensors(header, tensors)


def state_tensors(state: TrainState) -> dict[str, torch.Tensor]:
    """The tensors of a TrainState by checkpoint name: param.NAME, adam.NAME.KEY, strategy.NAME."""
    tensors = {f"param.{n}": t for n, t in state.params.items()}
    tensors.update({f"adam.{n}.{k}": t for n, m in state.moments.items() for k, t in m.items()})
    tensors.update({f"strategy.{n}": t for n, t in state.strategy.items()})
    return tensors


def state_from_tensors(header: dict, tensors: dict[str, torch.Tensor]) -> TrainState:
    """Inverse of state_tensors; header holds step, kind and the kind's attributes (those it lacks:
    their defaults, as a checkpoint written before the attribute existed means)."""
    params, moments, strategy = {}, {}, {}
    for key, t in tensors.items():
        section, _, rest = key.partition(".")
        if section == "param":
            params[rest] = t
        elif section == "adam":
            name, _, field = rest.rpartition(".")
            moments.setdefault(name, {})[field] = t
        else:
            strategy[rest] = t
    kind = kinds.get(header["kind"])
    attrs = {name: header.get(name, default) for name, default in kind.default_attrs().items()}
    return TrainState(header["step"], kind.name, attrs, params, moments, strategy)


def mean_psnr(prims: kinds.Primitives, cameras: Sequence[Camera], images: torch.Tensor, *,
              background: Sequence[float], near: float = 0.01, max_pairs: int = 1 << 20,
              masks: torch.Tensor | None = None, supersample: int | None = None) -> float:
    """Mean PSNR (dB) of the renders, clamped to [0, 1], against images (N, H, W, 3) (over the
    valid pixels of masks (N, H, W), when given), rendered with `supersample` × `supersample` rays
    per pixel (default: the model's own, prims.supersample)."""
    supersample = prims.supersample if supersample is None else supersample
    total = 0.0
    with torch.no_grad():
        for k, (camera, image) in enumerate(zip(cameras, images)):
            color = render_supersampled(prims, camera, supersample, background=background, near=near,
                                        max_pairs=max_pairs).color
            mask = None if masks is None else masks[k].to(color.device)
            total += float(psnr(color.clamp(0, 1), image.to(color), mask))
    return total / len(cameras) if len(cameras) else math.nan
