"""`radfield bench-train`: milliseconds per training step, split into its parts.

The step is core/trainer/loop.py's loop body with `batch_views: 1` and the default `train` config,
timed part by part (the parts are run in the trainer's order, on its own functions):

    render forward    assemble the primitives, render(...)
    loss              the anisotropy regulariser's backward, the photometric loss (L1 + D-SSIM)
                      forward and backward down to the rendered image, the logged loss and PSNR
    render backward   from ∂L/∂image to every parameter
    optimiser         Adam step and zero_grad
    population        the strategy's per-view gradient statistics (accumulate) and refine

Population control keeps the primitive count fixed (densification starts after the run), so
each row measures one count: `refine` then costs its checks only. The `train()` column times the
real `loop.train`, end to end, as a check that the parts add up: one run of warm-up + steps
steps, clocked by its on_step callback (at the reads of the step statistics, every `warmup` steps:
on a GPU the steps between them run ahead of the device), gives the ms per step after the warm-up,
with the SH degree schedule at its last stage from step 3 on (as the parts, which render at the
full degree); the `setup` column is the rest of the call in ms: its set-up (copies of the
parameters and images, the optimiser, the strategy) and the warm-up steps, paid once per call.

The `peak MiB` column is the most memory held while the timed steps ran (the parameters, the
images, Adam's moments and a step's intermediates): on the CPU the process's peak resident set size
(its high-water mark, reset before the timed steps through /proc/self/clear_refs; where that cannot
be reset, the process's peak so far), on CUDA torch's peak allocated memory (reset likewise). It is
what a training run of that size needs, e.g. against a machine's memory.

The scene is bench-render's (primitives over a sphere's surface, orbit cameras); the targets are
renders of the same scene with its colours shifted, so the loss and its gradients are not zero.
Absolute times depend on the machine and its load: compare ratios within one run.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from radfield.bench.render import bench_cameras, bench_models, reference_twin
from radfield.core.train.losses import anisotropy, photometric, psnr
from radfield.core.render.rasterize import render
from radfield.core.trainer.loop import make_strategy
from radfield.core.trainer import loop

PARTS = ("forward", "loss", "backward", "optimiser", "population")


@dataclass
class StepTiming:
    ms: dict[str, float]   # mean ms per step of each part
    train_ms: float        # marginal ms per step of loop.train, end to end
    setup_ms: float        # loop.train's cost once per call
    pairs: float           # evaluated pixel-primitive pairs per step
    peak_mib: float        # the most memory held during the timed steps (module docstring)

    @property
    def total_ms(self) -> float:
        return sum(self.ms.values())


def bench_config(steps: int) -> dict:
    """The default `train` section with population control that never changes the count."""
    from radfield.pipeline.config import load_defaults

    cfg = load_defaults()["train"]
    cfg["iterations"] = steps
    cfg["batch_views"] = 1
    cfg["densify"]["start"] = steps + 1          # statistics every step, no refinement
    cfg["densify"]["stop"] = steps + 1
    # no checkpoint within the run, and the rules that refresh what they derive from the geometry
    # (frequency cap, view cones: strategy.refresh_interval) refresh every densify.every steps as
    # in a default run, not every step
    every = cfg["densify"]["every"]
    cfg["checkpoint_every"] = every * math.ceil((steps + 1) / every)
    return cfg


def reset_peak_memory(device: torch.device) -> None:
    """Start measuring the peak from now: CUDA's peak allocated memory, or on Linux the process's
    high-water mark of resident memory (clear_refs "5", Linux >= 4.0; elsewhere it cannot be reset)."""
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        return
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def peak_memory_mib(device: torch.device) -> float:
    """The peak since reset_peak_memory, in MiB: CUDA's allocated memory, else the resident set
    (getrusage's ru_maxrss, which follows the reset high-water mark on Linux; NaN without `resource`)."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    try:
        import resource
    except ImportError:   # not a Unix
        return float("nan")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 2**10   # bytes on macOS, KiB on Linux


def _targets(prims, cams, device):
    shifted = prims.map(lambda t: t.clone())
    shifted.sh[:, 0] += 0.4
    with torch.no_grad():
        return torch.stack([render(shifted.to(device), cam).color.clamp(0, 1) for cam in cams]).float()


def time_steps(prims, cams, images, cfg: dict, steps: int, warmup: int, device: str) -> StepTiming:
    """Time `steps` training steps (after `warmup` untimed ones), part by part, then run
    loop.train for as many steps, end to end."""
    dev = torch.device(device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    cfg = {**cfg, "sh_degree": prims.sh_degree}   # the model's own degree, as the train stage trains it
    state = loop.initial_state(prims, cfg["sh_degree"])
    params = {n: t.to(dev).clone().requires_grad_(True) for n, t in state.params.items()}
    optimizer = loop.make_optimizer(params, cfg["lr"], extent=1.0, kind=state.kind)
    strategy = make_strategy(state.kind, cfg["densify"], extent=1.0, near=0.01, max_primitives=None,
                             initial_count=len(prims))
    accumulators = strategy.init_state(len(prims), dev)
    bg = torch.ones(3, device=dev)
    totals = dict.fromkeys(PARTS, 0.0)
    pairs = 0.0
    degree = cfg["sh_degree"]   # the last stage of the SH schedule: the most expensive colour

    for step in range(warmup + steps):
        if step == warmup:
            sync()
            reset_peak_memory(dev)
        spent = dict.fromkeys(PARTS, 0.0)
        view = step % len(cams)

        def clock(part, start):
            sync()
            now = time.perf_counter()
            spent[part] += now - start
            return now

        t = time.perf_counter()
        (cfg["lambda_aniso"] * anisotropy(params["log_scales"])).backward()
        t = clock("loss", t)
        before = {n: None if params[n].grad is None else params[n].grad.clone() for n in strategy.grad_names}
        t = clock("population", t)
        out = render(loop.assemble(params, state.kind, state.attrs), cams[view], background=bg, sh_degree=degree)
        t = clock("forward", t)
        image = out.color.detach().requires_grad_(True)
        loss = photometric(image, images[view], cfg["lambda_dssim"])
        loss.backward()
        float(loss.detach()), float(psnr(image.detach().clamp(0, 1), images[view]))
        t = clock("loss", t)
        out.color.backward(image.grad)
        t = clock("backward", t)
        grads = {n: loop.own_gradient(params[n].grad, before[n], 1) for n in strategy.grad_names}
        strategy.accumulate(accumulators, params, grads, cams[view], step + 1)
        t = clock("population", t)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        t = clock("optimiser", t)
        strategy.refine(accumulators, params, optimizer, step + 1, loop.generator(0, 1, step))
        clock("population", t)
        if step >= warmup:
            for part in PARTS:
                totals[part] += spent[part]
            pairs += out.meta["pairs"]

    sync()
    peak = peak_memory_mib(dev)
    train_ms, setup_ms = time_train(prims, cams, images, steps, warmup, dev, sync)
    return StepTiming({p: 1e3 * v / steps for p, v in totals.items()}, train_ms, setup_ms, pairs / steps, peak)


def time_train(prims, cams, images, steps: int, warmup: int, device, sync) -> tuple[float, float]:
    """loop.train's ms per step after `warmup` steps, and the rest of the call (see the module
    docstring), from one run of warmup + steps steps."""
    cfg = bench_config(warmup + steps)
    # the model's own SH degree, as the train stage trains it (3; the relightable kinds' 0), reached
    # from step 3 on: the parts' colour
    cfg["sh_degree"], cfg["sh_increase_every"] = prims.sh_degree, 1
    # the step statistics are read (and on_step called, in a burst) at the end of the warm-up and
    # every `warmup` steps after it: the clock needs those two ends, and a GPU then runs ahead of
    # the host in between as it does in a real run (train.log_every: 50), not one step at a time
    cfg["log_every"] = max(warmup, 1)
    clock = []   # the time on_step saw each step (at the read that handed it over)

    def on_step(step, info):
        sync()
        clock.append(time.perf_counter())

    start = time.perf_counter()
    loop.train(prims, cams, images, cfg, background=(1.0, 1.0, 1.0), extent=1.0, seed=0, device=device,
                  on_step=on_step)
    sync()
    total = time.perf_counter() - start
    warm = clock[warmup - 1] if warmup else start
    per_step = (clock[-1] - warm) / steps
    return 1e3 * per_step, 1e3 * (total - steps * per_step)


def run_bench_train(counts=(2_000, 10_000, 20_000), sizes=(64, 256), kinds=("neural", "gaussian"), steps: int = 5,
                    warmup: int = 2, views: int = 4, device: str = "cpu", echo=print, advance=lambda: None,
                    baseline: bool = False) -> dict:
    """Print one row per (kind, count, size): ms per step of each part, their sum, loop.train's
    marginal ms per step and its set-up ms, evaluated pairs per second of the render forward, and the
    peak memory of the steps (module docstring).
    With `baseline`, each row is preceded by the same row on the reference twins
    (RADFIELD_KERNELS=torch, "torch") and followed by the speed-up of the sum and of train().
    Returns the figures."""
    cfg = bench_config(steps)
    echo(f"bench-train: {steps} timed steps (+{warmup} warm-up) per row, {views} orbit views, device={device}, "
         f"threads={torch.get_num_threads()}; ms per step")
    w = max(11, *map(len, kinds))   # the kind column fits the longest name
    echo(f"  {'kind':{w}s} {'count':>6s} {'size':>7s} {'path':>6s} " + " ".join(f"{p:>10s}" for p in PARTS)
         + f" {'sum':>8s} {'train()':>8s} {'setup':>7s} {'Mpairs/s':>9s} {'peak MiB':>9s}")
    results = {}
    for kind in kinds:
        for count in counts:
            prims = bench_models(count, (kind,))[kind]
            for size in sizes:
                cams = bench_cameras(views, size, size)
                images = _targets(prims, cams, device)
                rows = {}
                for path in (("torch", "fused") if baseline else ("fused",)):
                    with reference_twin(path == "torch"):
                        t = time_steps(prims, cams, images, cfg, steps, warmup, device)
                    rate = t.pairs / (t.ms["forward"] * 1e3) if t.ms["forward"] > 0 else float("nan")
                    echo(f"  {kind:{w}s} {count:6d} {size:3d}x{size:<3d} {path:>6s} "
                         + " ".join(f"{t.ms[p]:10.1f}" for p in PARTS)
                         + f" {t.total_ms:8.1f} {t.train_ms:8.1f} {t.setup_ms:7.1f} {rate:9.1f} {t.peak_mib:9.0f}")
                    rows[path] = {**t.ms, "sum": t.total_ms, "train": t.train_ms, "setup": t.setup_ms, "pairs": t.pairs,
                                  "peak_mib": t.peak_mib}
                if baseline:
                    before, after = rows["torch"], rows["fused"]
                    echo(f"  {'':{w}s} {'':6s} {'':7s} {'x':>6s} " + " ".join(f"{before[p] / after[p]:10.1f}" for p in PARTS)
                         + f" {before['sum'] / after['sum']:8.1f} {before['train'] / after['train']:8.1f}")
                    results[f"{kind}/{count}/{size}/torch"] = before
                results[f"{kind}/{count}/{size}"] = rows["fused"]
                advance()
    return results
