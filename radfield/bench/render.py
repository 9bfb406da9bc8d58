"""`radfield bench-render`: time the renderer on neural primitives and 3D Gaussians side by side.

The scene imitates a trained object: primitives scattered over a unit sphere's surface (where
training puts them), seen from cameras on an orbit. Every kind of the registry (radfield.core.kinds:
`bench_models`) gets the same centres, rotations, SH and cameras, and the same footprint: a neural
primitive's ellipsoid has radii s and the Gaussian σ = s/3, so the Gaussian's 3σ splat covers the
same pixels. Neural primitives are timed with the windowed density of the defaults (render.window)
and with the hard-edged ellipsoid ("neural-hard"). The figures that matter
are ratios measured in one run; absolute times depend on the machine and its load. On CUDA the
device is synchronised before every clock reading (radfield.util.timing), so a time is the work's.
"""

from __future__ import annotations

import contextlib
import math
import os
import warnings
from dataclasses import dataclass

import torch

from radfield.core import kinds as registry
from radfield.core.geometry.cameras import Camera, Light, look_at
from radfield.core.render.rasterize import render
from radfield.core.splat.sh import num_sh_coeffs
from radfield.util.timing import clock


@contextlib.contextmanager
def reference_twin(enabled: bool = True):
    """Within the block the renderer and the loss run their readable torch twins
    (RADFIELD_KERNELS=torch, read at every call): the "before" of a before/after table."""
    saved = os.environ.get("RADFIELD_KERNELS")
    if enabled:
        os.environ["RADFIELD_KERNELS"] = "torch"
    try:
        yield
    finally:
        if saved is None:
            os.environ.pop("RADFIELD_KERNELS", None)
        else:
            os.environ["RADFIELD_KERNELS"] = saved


# every registered kind's benchmark variants ("neural" (the windowed density of the defaults),
# "neural-hard" (the paper's hard-edged ellipsoid), "gaussian", "neural-dynamic", ...); bench-train
# takes any of them (--kinds), bench-render's rows are those of the kinds a plain view draws (no
# conditions such as a time)
ALL_BENCH_KINDS = tuple(variant for kind in registry.registered() for variant in kind.bench_variants)
BENCH_KINDS = tuple(variant for kind in registry.registered() if not kind.conditions for variant in kind.bench_variants)


def bench_models(num: int, kinds=BENCH_KINDS, scale: float = 0.04, sh_degree: int = 3, seed: int = 0) -> dict:
    """{variant: primitives} of the benchmark scene for the variants `kinds`: one set of centres,
    rotations, SH and radii s, which each registered kind turns into its primitives (in registration
    order, drawing what it needs from the scene's generator)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.nn.functional.normalize(torch.randn(num, 3, generator=g), dim=-1)
    means = means * (1 + 0.02 * torch.randn(num, 1, generator=g))
    log_scales = torch.log(scale * (0.5 + torch.rand(num, 3, generator=g)))
    quats = torch.randn(num, 4, generator=g)
    sh = torch.randn(num, num_sh_coeffs(sh_degree), 3, generator=g) * 0.3
    scene = {"means": means, "log_scales": log_scales, "quats": quats, "sh": sh}
    models = {}
    for kind in registry.registered():
        models.update(kind.bench_models(scene, g))
    return {variant: models[variant] for variant in kinds}


def bench_scene(num: int, scale: float = 0.04, sh_degree: int = 3, seed: int = 0):
    """(windowed neural primitives, Gaussians) of the benchmark scene (bench_models), as the
    distributed benchmark and the study scripts compare them."""
    models = bench_models(num, ("neural", "gaussian"), scale, sh_degree, seed)
    return models["neural"], models["gaussian"]


def bench_cameras(count: int, width: int, height: int) -> list[Camera]:
    """`count` views on an orbit around the scene; each shows its own moment (i + ½)/count and is lit
    by a point light above the scene, which time-conditioned and relightable kinds draw and every
    other kind ignores."""
    focal = 0.5 * width / math.tan(math.radians(25))
    cams = []
    for i in range(count):
        a = 2 * math.pi * i / count
        eye = (3.2 * math.cos(a), 3.2 * math.sin(a), 1.0)
        cams.append(Camera(fx=focal, fy=focal, cx=width / 2, cy=height / 2, width=width, height=height,
                           c2w=look_at(eye, (0, 0, 0)), name=f"orbit{i}",
                           conditions={"time": (i + 0.5) / count,
                                       "light": Light(position=(0.0, 0.0, 3.0), intensity=9.0)}))
    return cams


@dataclass
class Timing:
    forward_ms: float
    backward_ms: float   # forward + backward
    pairs: float         # evaluated pixel-primitive pairs per frame
    contributing: float  # pairs that added to a pixel


def time_model(prims, cams, repeats: int, device: str) -> Timing:
    prims = prims.to(device)
    for cam in cams[:1]:  # warm-up
        render(prims, cam)
        p = prims.map(lambda t: t.clone().requires_grad_(True))
        render(p, cam).color.sum().backward()
    fwd, pairs, contrib = [], [], []
    with torch.no_grad():
        for _ in range(repeats):
            for cam in cams:
                t = clock(device)  # CUDA runs asynchronously: read the clock only on an idle device
                out = render(prims, cam)
                fwd.append(clock(device) - t)
                pairs.append(out.meta["pairs"])
                contrib.append(out.meta["contributing_pairs"])
    bwd = []
    params = prims.map(lambda t: t.clone().requires_grad_(True))
    for _ in range(repeats):
        for cam in cams:
            t = clock(device)
            out = render(params, cam)
            (out.color - 0.5).abs().mean().backward()
            bwd.append(clock(device) - t)
    mean = lambda xs: sum(xs) / len(xs)
    return Timing(1e3 * mean(fwd), 1e3 * mean(bwd), mean(pairs), mean(contrib))


def run_bench(num: int = 10_000, width: int = 256, height: int = 256, views: int = 4, repeats: int = 2,
              device: str = "cpu", profile: bool = False, echo=print, baseline: bool = False) -> dict:
    """Print forward and forward+backward ms/frame of each kind of BENCH_KINDS; with `baseline`, first the
    reference twin's (RADFIELD_KERNELS=torch) in the same run, and the ratios."""
    models = bench_models(num)
    cams = bench_cameras(views, width, height)
    echo(f"bench-render: {num} primitives, {views} views of {width}x{height}, {repeats} repeats, "
         f"device={device}, threads={torch.get_num_threads()}")
    results, before = {}, {}
    for name, prims in models.items():
        if baseline:
            with reference_twin():
                t = time_model(prims, cams, repeats, device)
            before[name] = t
            echo(f"  {name:11s} torch twin  forward {t.forward_ms:8.1f} ms/frame   forward+backward {t.backward_ms:8.1f} ms/frame")
        t = time_model(prims, cams, repeats, device)
        results[name] = t
        echo(f"  {name:11s} forward {t.forward_ms:8.1f} ms/frame ({1e3 / t.forward_ms:.0f} FPS)   "
             f"forward+backward {t.backward_ms:8.1f} ms/frame   "
             f"{t.pairs / 1e6:.2f} M pairs/frame ({t.contributing / 1e6:.2f} M contributing)   "
             f"{t.pairs / t.forward_ms / 1e3:.2f} M pairs/s forward")
        if baseline:
            b = before[name]
            echo(f"  {name:11s} speed-up over the torch twin: forward {b.forward_ms / t.forward_ms:.2f}x, "
                 f"forward+backward {b.backward_ms / t.backward_ms:.2f}x")
    n, g = results["neural"], results["gaussian"]
    echo(f"  neural/gaussian time ratio: forward {n.forward_ms / g.forward_ms:.2f}x, "
         f"forward+backward {n.backward_ms / g.backward_ms:.2f}x; per pair {(n.forward_ms / n.pairs) / (g.forward_ms / g.pairs):.2f}x")
    if profile:
        from torch.profiler import ProfilerActivity, profile as torch_profile
        activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if str(device).startswith("cuda") else [])
        for name, prims in models.items():
            params = prims.to(device).map(lambda t: t.clone().requires_grad_(True))
            with warnings.catch_warnings():
                # one cycle: torch 2.11's note that events of earlier cycles are cleared says nothing
                warnings.filterwarnings("ignore", message=".*Profiler clears events")
                with torch_profile(activities=activities) as prof:
                    render(params, cams[0]).color.sum().backward()
            costs = prof.key_averages()
            echo(f"\n  top costs, {name}, one forward+backward, by host time:")
            echo(costs.table(sort_by="self_cpu_time_total", row_limit=12))
            if len(activities) > 1:   # torch's launches and Triton's (the driver API's)
                echo(f"\n  top costs, {name}, one forward+backward, by device time (where the GPU's time goes):")
                echo(costs.table(sort_by="self_device_time_total", row_limit=12))
                launches = sum(e.count for e in costs if e.key in ("cudaLaunchKernel", "cuLaunchKernel", "cuLaunchKernelEx",
                                                                  "cudaLaunchKernelExC"))
                echo(f"  kernel launches, {name}, one forward+backward: {launches}")
    out = {k: vars(v) for k, v in results.items()}
    for k, v in before.items():
        out[f"{k}/torch"] = vars(v)
    return out
