"""The Triton GPU backend (core/backends/gpu/) against the readable torch twin: whole renders of
Gaussians and of neural primitives, hard-edged and windowed (image, alpha, depth, the renderer's
counts) and the gradient of every parameter, the densification statistics read from those
gradients, the tile binning, and that every kernel compiles for a GPU.

Without a GPU (CI) the very same kernels run on CPU tensors in Triton's interpreter: the variable
TRITON_INTERPRET=1 is set here, before anything imports triton, and the CPU path only takes the
backend inside `backends.using("triton")`. With a GPU (scripts/gpu_check.sh) the module runs the
compiled kernels on CUDA tensors instead. The views are tiny: the interpreter is slow.
"""

import itertools
import math
import os
import re

import pytest
import torch

if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")   # before the kernels are imported (at the first view)

from radfield.core import backends, kinds                   # noqa: E402
from radfield.core.backends import gpu                      # noqa: E402
from radfield.core.geometry.cameras import Camera, look_at  # noqa: E402
from radfield.core.kinds import random_gaussians, random_neural   # noqa: E402
from radfield.core.render.rasterize import render           # noqa: E402
from radfield.core.trainer.loop import make_strategy   # noqa: E402
from shared_helpers import (TOL32, assert_renders_close, float32_sensitivity, float64_twin,   # noqa: E402
                            projection_rows, render_with_grads)

IN_CI = os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")   # conftest.in_ci()
INSTALLED = gpu._installed()   # a Triton the kernels compile with (>= gpu.MIN_TRITON)
DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
# outside CI a machine where the backend cannot run these kernels (no Triton, the older one a CUDA
# torch before 2.8 pins, an interpreter that cannot run them) skips these tests; in CI they run
# (and fail) regardless
pytestmark = pytest.mark.skipif(not IN_CI and gpu.why_not() is not None, reason=f"{gpu.why_not()} (Linux x86-64; "
                                "CUDA builds of torch 2.8 and later bring Triton 3.4 or newer)")
TOL = {torch.float64: dict(rtol=1e-9, atol=1e-10), torch.float32: TOL32}


def test_triton_is_installed_and_runs_here():
    """CI fails here when triton is missing; the backend runs CUDA tensors with a GPU, or CPU tensors
    in the interpreter, but the CPU never takes it unless it is chosen."""
    assert INSTALLED, f"triton >= 3.4 is not installed ({gpu.why_not()}): the test extra installs it on Linux x86-64"
    assert backends.why_not(backends.TRITON) is None
    assert backends.TRITON not in backends.available("cpu", torch.float32)   # the CPU path is unchanged
    with backends.using(backends.TRITON):
        for kind in ("gaussian", "neural"):
            assert backends.select(DEVICE, torch.float32, kind=kind) == backends.TRITON
            assert backends.select(DEVICE, torch.float64, kind=kind) == backends.TRITON
        assert backends.select(DEVICE, torch.float16, kind="gaussian") == backends.TORCH


@pytest.mark.parametrize("version, why", [((3, 3), "triton 3.3 is older than 3.4"), (None, "triton is not installed")])
def test_a_missing_or_too_old_triton_is_refused_and_cuda_says_so(monkeypatch, capsys, version, why):
    # Triton 3.3 cannot compile the kernels (nested tuples from a jit function): the backend must not
    # run there, and --device cuda, which then runs the torch twins, says why in one line
    from radfield.cli.common import resolve_device

    monkeypatch.setattr(gpu, "_version", lambda: version)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert backends.why_not(backends.TRITON).startswith(why)
    assert not gpu.runs("cuda", torch.float32) and backends.select("cuda", torch.float32, kind="neural") == "torch"
    assert resolve_device("cuda") == torch.device("cuda")
    err = capsys.readouterr().err
    assert err.startswith(f"radfield: warning: --device cuda: {why}") and "torch 2.8 and later bring Triton 3.4" in err
    assert err.count("\n") == 1
    monkeypatch.setenv("RADFIELD_KERNELS", "torch")   # the user chose the twins: nothing to say
    resolve_device("cuda")
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("triton, numpy, fails", [((3, 6), (2, 5), True), ((3, 6), (2, 4), False),
                                                  ((3, 8), (2, 5), False)])
def test_an_interpreter_that_cannot_run_the_kernels_is_named(monkeypatch, triton, numpy, fails):
    # Triton 3.6 (the GPU machine's) with numpy 2.5 fails 26 of these tests in its interpreter on
    # one int() of a one-element array; the CPU says so instead (on a GPU the interpreter is not used)
    monkeypatch.setattr(gpu, "_version", lambda: triton)
    monkeypatch.setattr(gpu, "_numpy_version", lambda: numpy)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    why = gpu.why_not()
    assert (why is not None and why.startswith(f"the interpreter of triton 3.6 cannot run the kernels with numpy "
                                               f"2.5")) if fails else why is None
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert gpu.why_not() is None   # compiled for a GPU: no interpreter


def test_the_installed_triton_is_one_the_kernels_compile_with():
    assert gpu._version() >= gpu.MIN_TRITON, gpu._version()


def hard_scene(dtype):
    """48 Gaussians on a 37×21 view (tiles cut by both image edges): a dense, nearly opaque cluster
    (pixels terminate early, many splats per tile), splats behind the camera and straddling the
    near plane, splats partly off-screen, a large one over several tiles and faint ones (α below
    1/255 everywhere)."""
    prims = random_gaussians(48, sh_degree=1, scale=0.12, extent=0.5, seed=11)
    eye = torch.tensor([0.2, -2.5, 0.4])
    prims.opacities[:24] = 4.5                                   # σ(4.5) ≈ 0.99: the α clamp, termination
    prims.log_scales[:24] += math.log(2.0)
    prims.means[24:27] = eye + torch.tensor([[0.0, -0.5, 0.0], [0.1, -1.0, 0.2], [0.02, 0.04, 0.0]])   # behind / at the eye
    prims.means[27:31] = torch.tensor([[1.6, 0.0, 0.0], [-1.7, 0.2, 0.3], [0.0, 0.0, 1.1], [0.3, 0.1, -1.0]])   # image edges
    prims.log_scales[31] = math.log(0.6)                         # covers several tiles
    prims.opacities[32:35] = -9.0                                # α < 1/255: skipped
    cam = Camera(fx=34.0, fy=31.0, cx=18.1, cy=10.4, width=37, height=21, c2w=look_at(tuple(eye.tolist()), (0, 0, 0)))
    return prims.to(dtype=dtype, device=DEVICE), cam


def scene_of(name, dtype, render_scene):
    """hard_scene, or conftest.render_scene's (24×20, the backends' common case: for neural primitives
    the camera inside one, one straddling the near plane, one at the α clamp) of a kind; "neural-5":
    5 hidden units (the backward sums the units' gradients in groups of 8, the rest masked);
    "neural-dense": 40 primitives in one tile, a list longer than the forward's CHUNK (it counts
    the live pixels once a chunk). The last two are windowed: their hard-edged versions graze a
    silhouette at 1e-4 of a radius, where no float32 gradient is within the tolerance of float64
    (test_the_float32_scenes_are_well_posed); the hard-edged kernels' float32 case is "neural"."""
    if name == "hard_scene":
        return hard_scene(dtype)
    if name == "neural-5":
        prims, cam = render_scene("neural-window", dtype, hidden=5)
        assert prims.hidden == 5
    elif name == "neural-dense":
        prims = random_neural(40, sh_degree=1, scale=0.35, extent=0.3, b2=1.0, w2_amplitude=1.0, seed=5).to(dtype=dtype)
        prims.window = True
        cam = Camera(fx=14.0, fy=15.0, cx=8.2, cy=7.9, width=16, height=16, c2w=look_at((0.15, -1.5, 0.25), (0, 0, 0)))
    else:
        prims, cam = render_scene(name, dtype)
    return prims.to(device=DEVICE), cam


SCENES = ["gaussian", "hard_scene", "neural", "neural-window", "neural-5", "neural-dense"]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("scene", SCENES)
def test_render_matches_the_torch_twin(scene, dtype, render_scene):
    """float64: the kernels and the twin agree to rounding. float32: both are compared with the
    twin in float64 on the same rounded inputs (shared_helpers.float64_twin), each within TOL32;
    the two float32 paths agree on every count."""
    prims, cam = scene_of(scene, dtype, render_scene)
    fast, grads_fast = render_with_grads(prims, cam, backends.TRITON)
    slow, grads_slow = render_with_grads(prims, cam, backends.TORCH)
    assert slow.meta["contributing_pairs"] > 500
    if scene != "gaussian":   # the scenes do what they say: pixels terminate early
        assert slow.meta["terminated_pixels"] > 20
    if scene == "hard_scene":
        assert slow.meta["visible"] < len(prims.means)
    if scene == "neural-dense":   # one tile, its list longer than a chunk
        assert cam.width == cam.height == gpu.TILE and slow.meta["visible"] > gpu.tiles.CHUNK.value
    # evaluated pairs differ by design (the kernel skips a pixel as soon as it terminates, the twin
    # only between chunks); every other count is the same
    evaluated = fast.meta.pop("pairs"), slow.meta.pop("pairs")
    assert fast.meta == slow.meta and evaluated[0] <= evaluated[1]
    assert grads_fast.keys() == grads_slow.keys() == set(prims.tensors())
    assert all(gs.abs().max() > 0 for gs in grads_slow.values())
    if dtype == torch.float64:
        assert_renders_close(fast, grads_fast, slow, grads_slow, TOL[dtype])
    else:
        exact, grads_exact = float64_twin(prims, cam)
        assert_renders_close(fast, grads_fast, exact, grads_exact, TOL32, "triton float32: ")
        assert_renders_close(slow, grads_slow, exact, grads_exact, TOL32, "torch float32: ")


@pytest.mark.parametrize("scene", SCENES)
def test_the_float32_scenes_are_well_posed(scene, render_scene):
    """A float32 render is within TOL32 of float64 on every CPU only where the scene allows it:
    moving every parameter by 4 float32 ulps moves the float64 image and gradients by well under
    the tolerance (a quarter of it). A gradient kink at one pair (a ray entering exactly at the
    near plane, a sphere's tied max(s)) or a hard silhouette grazed at 1e-4 of a radius breaks it:
    whether float32 lands on the float64 side then depends on the CPU's last bits (on an AVX2 MKL
    the twin did not, and test_render_matches_the_torch_twin failed there)."""
    prims, cam = scene_of(scene, torch.float32, render_scene)
    sensitivity = float32_sensitivity(prims, cam)
    assert sensitivity <= TOL32["atol"] / 4, f"{scene}: 4 float32 ulps move the float64 render by {sensitivity:.2g}"


@pytest.mark.parametrize("kind", ["gaussian", "neural"])
def test_densification_statistics_match_the_torch_twin(kind, densify_config, render_scene):
    """What population control reads of a view (core/train/strategy.py: for Gaussians the screen-space
    signal from the means' gradient, for neural primitives the MLP gradients' norms, and the
    visibility count) is the same after a Triton render as after the twin's."""
    prims, cam = scene_of("hard_scene" if kind == "gaussian" else "neural", torch.float32, render_scene)
    p = len(prims.means)
    strategy = make_strategy(kind, densify_config(), extent=1.0, near=0.05, max_primitives=None, initial_count=p)
    params = {name: t.detach() for name, t in prims.tensors().items()}
    states = []
    for backend in (backends.TRITON, backends.TORCH):
        grads = render_with_grads(prims, cam, backend)[1]
        state = strategy.init_state(p, DEVICE)
        strategy.accumulate(state, params, grads, cam, step=1)
        states.append(state)
    assert torch.equal(states[0]["count"], states[1]["count"]) and states[1]["count"].sum() > 0
    assert states[1]["grad"].max() > 0
    torch.testing.assert_close(states[0]["grad"], states[1]["grad"], rtol=1e-3, atol=1e-7)


@pytest.mark.parametrize("kind", ["gaussian", "neural"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_statistics_kernel_matches_the_torch_twin(kind, dtype, strategy_scene, densify_config):
    """Ops "gaussian_accumulate" / "neural_accumulate" on Triton (statistics_kernels.py) against the
    twin of `_Strategy.accumulate`: 4000 primitives spread well beyond the frustum, two views
    (counts 0, 1 and 2), added into accumulators that already hold something."""
    params, grads, cam = strategy_scene(kind, dtype)
    params = {n: t.to(DEVICE) for n, t in params.items()}
    grads = {n: t.to(DEVICE) for n, t in grads.items()}
    strategy = make_strategy(kind, densify_config(), extent=1.0, near=0.05, max_primitives=None, initial_count=4000)
    other = Camera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, look_at((-2.5, 2.0, 0.5), (0.2, 0.0, 0.0)))
    states = []
    for backend in (backends.TRITON, backends.TORCH):
        state = {k: v.to(dtype) for k, v in strategy.init_state(4000, DEVICE).items()}
        state["grad"] += 0.25   # the op adds into what is there
        with backends.using(backend):
            assert (backends.kernel(strategy.statistics_op, DEVICE, dtype) is None) == (backend == backends.TORCH)
            for c in (cam, other):
                strategy.accumulate(state, params, grads, c, step=1)
        states.append(state)
    fast, slow = states
    assert torch.equal(fast["count"], slow["count"])
    assert set(slow["count"].unique().tolist()) == {0.0, 1.0, 2.0}
    tol = dict(rtol=1e-5, atol=1e-9) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(fast["grad"], slow["grad"], **tol)
    assert (fast["grad"][slow["count"] == 0] == 0.25).all()


def test_an_empty_view_renders_the_background():
    """Every splat behind the camera: nothing is drawn, T = 1, and every gradient is zero."""
    prims, cam = hard_scene(torch.float32)
    prims.means = prims.means + 10.0 * torch.tensor([0.2, -2.5, 0.4], device=DEVICE)   # all far behind the eye
    out, grads = render_with_grads(prims, cam, backends.TRITON)
    assert out.meta["visible"] == 0 and out.meta["candidate_pairs"] == 0
    torch.testing.assert_close(out.alpha, torch.zeros_like(out.alpha))
    torch.testing.assert_close(out.color, torch.tensor([0.2, 0.3, 0.4], device=DEVICE).expand_as(out.color))
    assert all(torch.count_nonzero(g) == 0 for g in grads.values())


@pytest.mark.parametrize("scene", ["hard_scene", "neural"])
def test_the_forward_writes_every_output_it_allocates(scene, monkeypatch, render_scene):
    """The forward's outputs are allocated, not filled (gpu/views.py: _outputs): with them filled
    by garbage first (NaN, −7) the render, its counts and its gradients are still the twin's, the
    empty view (every tile's list empty) still the background."""
    from radfield.core.backends.gpu import views

    allocate = views._outputs

    def garbage(*args):
        outputs = allocate(*args)
        for t in outputs:
            t.fill_(float("nan") if t.is_floating_point() else -7)
        return outputs

    monkeypatch.setattr(views, "_outputs", garbage)
    prims, cam = scene_of(scene, torch.float64, render_scene)
    fast, grads_fast = render_with_grads(prims, cam, backends.TRITON)
    slow, grads_slow = render_with_grads(prims, cam, backends.TORCH)
    fast.meta.pop("pairs"), slow.meta.pop("pairs")
    assert fast.meta == slow.meta
    for name in ("color", "alpha", "depth"):
        torch.testing.assert_close(getattr(fast, name), getattr(slow, name), **TOL[torch.float64])
    for name, gs in grads_slow.items():
        torch.testing.assert_close(grads_fast[name], gs, **TOL[torch.float64])
    prims.means = prims.means + 10.0 * (torch.as_tensor(cam.center, dtype=prims.means.dtype, device=DEVICE)
                                        - prims.means.mean(0))   # all far behind the eye
    out, _ = render_with_grads(prims, cam, backends.TRITON)
    assert out.meta["visible"] == 0 and bool(torch.isfinite(out.color).all()) and bool((out.alpha == 0).all())


# "gaussian-relight" runs the Gaussian kernels with the relightable colour's preparation on top, so
# the plain Gaussian kind adds nothing here but 10 s of CI
@pytest.mark.parametrize("kind", ["neural", "neural-dynamic", "gaussian-relight"])
def test_a_training_step_reads_the_device_once_a_view(kind, training_reads):
    """loop.train on the Triton path (the code a GPU runs: the kernels, the per-view preparation
    in torch, a conditioned kind's primitives of the view, loss, D-SSIM, Adam, the strategy's
    statistics, the rules), 4 steps of 2 views with log_every 2: between the reads of the step
    records (steps 2 and 4) the host reads one number a view, the binning's pair count
    (binning.pair_count), and nothing else: no render counter, no visible count (conftest.HostReads;
    the blocking copies to the device are test_cuda.py's)."""
    from radfield.core.geometry.cameras import Light
    from radfield.core.kinds import random_neural
    from radfield.core.trainer import loop
    from radfield.pipeline.config import load_defaults

    cams = [Camera(fx=20.8, fy=20.8, cx=8, cy=8, width=16, height=16, name=f"v{i}",
                   c2w=look_at((3 * math.cos(i), 3 * math.sin(i), 0.5), (0, 0, 0))) for i in range(3)]
    with torch.no_grad():
        images = torch.stack([render(random_neural(30, seed=1), c).color.clamp(0, 1) for c in cams])
    if kind.endswith("dynamic"):
        cams = [c.at(time=i / 2) for i, c in enumerate(cams)]
    if kind.endswith("relight"):
        cams = [c.at(light=Light(position=(2.0, i - 1.0, 2.0))) for i, c in enumerate(cams)]
    cfg = load_defaults()["train"]
    cfg.update(iterations=4, batch_views=2, log_every=2, checkpoint_every=100, eval_every=0, nonnegative_density=180.0,
               min_footprint=0.5, ray_jitter=0.5, random_background=True, sh_degree=0)
    cfg["densify"].update(start=1, stop=100, every=100)   # gathers the statistics every step, refines never
    start = (random_neural if kind.startswith("neural") else random_gaussians)(20, seed=2)
    geometry = {name: getattr(start, name) for name in ("means", "log_scales", "quats", "sh")}
    start = kinds.get(kind).from_points(geometry, kinds.get(kind).init_settings(load_defaults()), seed=0)
    log = []
    with backends.using(backends.TRITON), training_reads as reads:
        loop.train(start, cams, images, cfg, background=(1.0, 1.0, 1.0), extent=1.0, seed=0,
                      device=DEVICE, alphas=torch.ones(3, 16, 16), on_step=lambda step, info: log.append(step))
    assert log == list(range(1, 5))
    per_step = {step: sorted(f"{op} {where}" for s, op, where in reads.seen if s == step) for step in range(1, 5)}
    pair_counts = ["__int__ radfield.core.backends.gpu.binning.pair_count"] * 2
    for step, seen in per_step.items():
        if step in (2, 4):
            assert seen == sorted([*pair_counts, "tolist radfield.core.trainer.loop.flush"]), (step, seen)
        else:
            assert seen == pair_counts, (step, seen)


@pytest.mark.parametrize("kind", ["neural", "gaussian"])
def test_training_on_the_triton_path_is_the_twins(kind):
    """loop.train, 2 steps of 2 views each, on the Triton path (the views, the loss, the
    projection, the statistics: gradients of two views summed into one buffer's views) and on the
    torch twins: the same parameters after the last step, to float32 rounding."""
    from radfield.core.kinds import random_neural
    from radfield.core.trainer import loop
    from radfield.pipeline.config import load_defaults

    cams = [Camera(fx=20.8, fy=20.8, cx=8, cy=8, width=16, height=16, name=f"v{i}",
                   c2w=look_at((3 * math.cos(i), 3 * math.sin(i), 0.5), (0, 0, 0))) for i in range(3)]
    with torch.no_grad():
        images = torch.stack([render(random_neural(30, seed=1), c).color.clamp(0, 1) for c in cams])
    states = []
    for backend in (backends.TRITON, backends.TORCH):
        cfg = load_defaults()["train"]
        cfg.update(iterations=2, batch_views=2, log_every=100, checkpoint_every=100, eval_every=0, sh_degree=1,
                   nonnegative_density=180.0)
        cfg["densify"].update(start=1, stop=100, every=100)
        start = (random_neural if kind == "neural" else random_gaussians)(20, seed=2, sh_degree=1)
        geometry = {name: getattr(start, name) for name in ("means", "log_scales", "quats", "sh")}
        start = kinds.get(kind).from_points(geometry, kinds.get(kind).init_settings(load_defaults()), seed=0)
        with backends.using(backend):
            states.append(loop.train(start, cams, images, cfg, background=(1.0, 1.0, 1.0), extent=1.0, seed=0,
                                        device=DEVICE))
    fast, slow = states
    assert fast.step == slow.step == 2 and fast.params.keys() == slow.params.keys()
    for name, theirs in slow.params.items():
        torch.testing.assert_close(fast.params[name].cpu(), theirs.cpu(), rtol=1e-4, atol=2e-5, msg=name)
    assert not torch.equal(slow.params["log_scales"].cpu(), start.tensors()["log_scales"])   # training moved them


@pytest.mark.parametrize("kind", ["neural", "gaussian"])
def test_the_launches_of_a_view_do_not_grow_with_the_primitives(kind):
    """The torch ops of one forward + backward on the Triton path (each a kernel launch on a GPU,
    counted by a dispatch mode below autograd, so the backward's too; the ops that launch nothing,
    views and detaches, left out, and the interpreter's own copies of the kernels' arguments) are
    the same for 50 and for 200 primitives: nothing is done per primitive or per pair on the host.
    And they are few: 53 for neural primitives and 54 for Gaussians when this was written (611 and
    628 with the preparation and the binning in torch), besides the 8-9 Triton launches. (The torch twin's ops
    grow with the pairs: one set a chunk.)"""
    import sys

    from torch.utils._python_dispatch import TorchDispatchMode

    from radfield.bench.render import bench_cameras, bench_models

    no_kernel = {"view", "_unsafe_view", "_reshape_alias", "as_strided", "t", "transpose", "expand", "slice", "select",
                 "unsqueeze", "squeeze", "permute", "detach", "alias", "unbind", "split", "split_with_sizes",
                 "lift_fresh", "empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided"}

    class Launches(TorchDispatchMode):
        count = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            frame = sys._getframe(1)
            while frame is not None and frame.f_globals.get("__name__", "").split(".")[0] != "triton":
                frame = frame.f_back
            self.count += frame is None and func.__name__.split(".")[0] not in no_kernel   # (not the interpreter's)
            return func(*args, **(kwargs or {}))

    cam = bench_cameras(1, 32, 32)[0]
    counts = []
    for n in (50, 200):
        prims = bench_models(n, (kind,))[kind].to(device=DEVICE).map(lambda t: t.clone().requires_grad_(True))
        with backends.using(backends.TRITON), Launches() as launches:
            out = render(prims, cam)
            (out.color.sum() + out.alpha.sum()).backward()
        assert out.meta["visible"] > n / 4
        counts.append(launches.count)
    assert counts[0] == counts[1] and 0 < counts[0] <= 100, counts


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("shape", [(2, 13, 21, 3), (1, 4, 6, 3)])
def test_photometric_loss_matches_the_torch_twin(shape, dtype):
    """Op "photometric" on Triton ((1 − λ) L1 + λ D-SSIM in four launches) against the twin
    (losses._photometric): the value and the image gradient, for two images of odd sizes and for
    one smaller than the 11×11 window (every window crosses the zero padding), with pixels where
    the images tie (L1's gradient 0) and an upstream gradient other than 1."""
    from radfield.core.train import losses

    g = torch.Generator().manual_seed(0)
    x = torch.rand(shape, generator=g, dtype=dtype).to(DEVICE)
    y = torch.rand(shape, generator=g, dtype=dtype).to(DEVICE)
    y[0, 1, 2:4] = x[0, 1, 2:4]
    results = []
    for backend in (backends.TRITON, backends.TORCH):
        img = x.clone().requires_grad_(True)
        with backends.using(backend):
            assert (backends.kernel("photometric", DEVICE, dtype) is not None) == (backend == backends.TRITON)
            value = losses.photometric(img, y, 0.3)
        (2.5 * value).backward()
        results.append((value.detach(), img.grad))
    (fast, g_fast), (slow, g_slow) = results
    torch.testing.assert_close(fast, slow, **TOL[dtype])
    assert g_slow.abs().max() > 0
    torch.testing.assert_close(g_fast / g_slow.abs().max(), g_slow / g_slow.abs().max(), **TOL[dtype])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_nonnegative_projection_matches_the_torch_twin(dtype):
    """Op "project_nonnegative_" on Triton (one lane per primitive) against the twin
    (core/train/positivity.py: project_nonnegative): rows inside the cone, ties, the polar cone,
    zeros, widths 1-16; only the masked rows change, and they land in the cone."""
    from radfield.core.train.positivity import project_nonnegative

    g = torch.Generator().manual_seed(5)
    for width in (1, 3, 8, 16):
        w2, b2, mask = projection_rows(width, dtype, g)
        expect_w2, expect_b2 = project_nonnegative(w2, b2)
        fast_w2, fast_b2 = w2.clone().to(DEVICE), b2.clone().to(DEVICE)
        with backends.using(backends.TRITON):
            backends.kernel("project_nonnegative_", DEVICE, dtype)(fast_w2, fast_b2, mask.to(DEVICE))
        fast_w2, fast_b2 = fast_w2.cpu(), fast_b2.cpu()
        tol = dict(rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-12)
        torch.testing.assert_close(fast_w2[mask], expect_w2[mask], **tol)
        torch.testing.assert_close(fast_b2[mask], expect_b2[mask], **tol)
        assert torch.equal(fast_w2[~mask], w2[~mask]) and torch.equal(fast_b2[~mask], b2[~mask])
        assert bool((fast_w2[mask].abs().sum(-1) <= fast_b2[mask] + 1e-5).all())
        assert not torch.equal(fast_w2[mask], w2[mask]) and (fast_b2[40:60][mask[40:60]] == 0).all()


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_colour_matches_the_torch_twin(degree, dtype):
    """Op "sh_color" on Triton (prepare_kernels.py) against sh_to_color(sh, normalize(v)): the colours
    and the gradients of sh and v, for 300 primitives (3 programs, the last one part full) with
    more coefficients than the degree reads, colours clamped at 0 (SH pulled below −0.5), and v of
    every length (a tiny one included)."""
    from radfield.core.splat.sh import sh_to_color

    g = torch.Generator().manual_seed(degree)
    sh = (torch.randn(300, 16, 3, generator=g, dtype=torch.float64) * 0.6).to(device=DEVICE, dtype=dtype)
    sh[:40, 0] = -3.0                                                     # colour clamped at 0
    v = (torch.randn(300, 3, generator=g, dtype=torch.float64) * torch.rand(300, 1, generator=g, dtype=torch.float64)
         * 5).to(device=DEVICE, dtype=dtype)
    v[7] = torch.tensor([1e-3, -2e-3, 5e-4])
    weights = torch.randn(300, 3, generator=g, dtype=torch.float64).to(device=DEVICE, dtype=dtype)
    results = []
    for backend in (backends.TRITON, backends.TORCH):
        inputs = [t.clone().requires_grad_(True) for t in (sh, v)]
        with backends.using(backend):
            op = backends.kernel("sh_color", DEVICE, dtype)
            assert (op is not None) == (backend == backends.TRITON)
            color = op(*inputs, degree) if op else sh_to_color(inputs[0], torch.nn.functional.normalize(inputs[1], dim=-1), degree)
        (color * weights).sum().backward()
        # (degree 0: the twin's colour does not depend on v, so v has no gradient there: zero)
        results.append((color.detach(), *(torch.zeros_like(t) if t.grad is None else t.grad for t in inputs)))
    assert (results[1][0] == 0).any() and (results[1][0] > 0).any()
    for name, fast, slow in zip(("colour", "d/dsh", "d/dv"), *results):
        torch.testing.assert_close(fast, slow, **TOL[dtype], msg=lambda m: f"{name}: {m}")
    assert (results[0][1][:, (degree + 1) ** 2:] == 0).all()   # coefficients beyond the degree: no gradient


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_neural_bounds_are_the_twins(dtype):
    """gpu.neural_bounds (one launch) against splat/view.py ellipsoid_bounds: the same boxes and
    visibility for 400 ellipsoids around a camera close to them (some behind it, some cut by the
    near plane: the whole image, some off-screen), on a 37×21 view."""
    from radfield.core.splat.view import ViewFrame
    from radfield.core.kinds import random_neural
    from radfield.core.splat.view import ellipsoid_bounds

    prims = random_neural(400, extent=1.2, scale=0.25, seed=4).to(dtype=dtype, device=DEVICE)
    cam = Camera(fx=30.0, fy=28.0, cx=18.3, cy=10.1, width=37, height=21, c2w=look_at((0.3, -1.0, 0.2), (0, 0, 0)))
    c2w = cam.c2w.to(dtype=dtype, device=DEVICE)
    w2c = torch.linalg.inv(c2w)
    means_cam = prims.means @ w2c[:3, :3].T + w2c[:3, 3]
    intrinsics = torch.tensor([cam.fx, cam.fy, cam.cx, cam.cy, 0.05], dtype=dtype, device=DEVICE)
    frame = ViewFrame(cam, c2w, w2c, c2w[:3, 3], means_cam, means_cam[:, 2], intrinsics, 0.05)
    with backends.using(backends.TRITON):
        bounds, visible = gpu.neural_bounds(prims, frame)
    twin_bounds, twin_visible = ellipsoid_bounds(prims, frame)
    assert torch.equal(visible, twin_visible) and 50 < int(visible.sum()) < 400
    assert torch.equal(bounds[visible].long(), twin_bounds[visible])
    whole = torch.tensor([0, 0, 36, 20], device=DEVICE)
    assert (twin_bounds[twin_visible] == whole).all(-1).any()   # some cut by the near plane
    assert (means_cam[:, 2] < 0).any()


def test_tile_lists_are_every_touched_tile_front_to_back():
    """bin_tiles against a loop over boxes and tiles: each tile lists exactly the visible boxes that
    touch it, in the depth order given; the invisible ones (their boxes anything, even inverted or
    far outside the image: the renderer passes every primitive) are in no list."""
    g = torch.Generator().manual_seed(3)
    width, height = 53, 37                     # 4 × 3 tiles, the last ones cut
    corner = torch.stack([torch.randint(0, width, (40,), generator=g), torch.randint(0, height, (40,), generator=g)], -1)
    size = torch.randint(0, 30, (40, 2), generator=g)
    far = torch.minimum(corner + size, torch.tensor([width - 1, height - 1]))
    bounds = torch.cat([corner, far], -1)
    visible = torch.rand(40, generator=g) < 0.7
    bounds[~visible] = torch.randint(-10**6, 10**6, (int((~visible).sum()), 4), generator=g)
    order = torch.randperm(40, generator=g)    # front to back
    offsets, entries = gpu.bin_tiles(bounds.to(DEVICE), visible.to(DEVICE), order.to(DEVICE), height, width)
    tiles_x, tiles_y = math.ceil(width / 16), math.ceil(height / 16)
    assert offsets.shape == (tiles_x * tiles_y + 1,) and offsets.dtype == entries.dtype == torch.int32
    offsets, entries, bounds = offsets.cpu().tolist(), entries.cpu().tolist(), bounds.tolist()
    for ty, tx in itertools.product(range(tiles_y), range(tiles_x)):
        t = ty * tiles_x + tx
        expected = [i for i in order.tolist() if visible[i] and bounds[i][0] // 16 <= tx <= bounds[i][2] // 16
                    and bounds[i][1] // 16 <= ty <= bounds[i][3] // 16]
        assert entries[offsets[t]:offsets[t + 1]] == expected, (tx, ty)
    assert offsets[0] == 0 and offsets[-1] == len(entries) and 0 < visible.sum() < 40


# Compiles every kernel for an H100 (sm_90) with no GPU, with the backend's options: Triton's front
# end, its lowering to PTX and the ptxas its wheel ships, so an error only the compiled kernels have
# (the interpreter runs Python) fails here in CI too; ptxas's log says whether a kernel spills
# registers to memory. In a fresh process: this one imported the kernels for the interpreter.
COMPILE = r"""
import inspect, sys
import triton
from triton import knobs
from triton.backends.compiler import GPUTarget
from triton.compiler import ASTSource
from radfield.core.backends.gpu import (COMPILE_OPTIONS, NEURAL_BACKWARD_OPTIONS, PREPARE_OPTIONS, binning_kernels,
                                       gaussian_kernels, loss_kernels, neural_kernels, positivity_kernels,
                                       prepare_kernels, statistics_kernels)

knobs.nvidia.dump_ptxas_log = True   # ptxas -v's lines, on stdout

def compile_for_sm90(fn, options=COMPILE_OPTIONS, floats="*fp32", **constexprs):
    names = list(inspect.signature(fn.fn).parameters)
    ints = {"height", "width", "tiles_x", "N", "P", "K", "total", "channels", "count"}
    ints32 = {"offsets_ptr", "entries_ptr", "bounds_ptr", "last_ptr", "counts_ptr"}
    ints64 = {"order_ptr", "place_ptr", "touched_ptr", "ends_ptr", "keys_ptr"}   # the binning's
    signature = {n: "constexpr" if n in constexprs else "i32" if n in ints else "*i32" if n in ints32
                 else "*i64" if n in ints64 else "*i8" if n in ("visible_ptr", "mask_ptr") else floats for n in names}
    source = ASTSource(fn, signature, constexprs={(names.index(k),): v for k, v in constexprs.items()})
    print("kernel", fn.fn.__name__, floats, sorted(constexprs.items()), flush=True)
    kernel = triton.compile(source, target=GPUTarget("cuda", 90, 32), options=options)
    assert len(kernel.asm["cubin"]) > 0
    # gradient sums need no memory order: Triton's default atomics (acq_rel) put a fence by each
    assert "acq_rel" not in kernel.asm["ptx"] and "fence" not in kernel.asm["ptx"], fn.fn.__name__
    return kernel

compile_for_sm90(gaussian_kernels.gaussian_forward, SIDE=16)
compile_for_sm90(gaussian_kernels.gaussian_backward, SIDE=16)
for window in (False, True):
    compile_for_sm90(neural_kernels.neural_forward, SIDE=16, UNITS=8, WINDOW=window)
    compile_for_sm90(neural_kernels.neural_backward, NEURAL_BACKWARD_OPTIONS[window], SIDE=16, UNITS=8, WINDOW=window)
compile_for_sm90(neural_kernels.neural_backward, NEURAL_BACKWARD_OPTIONS[False], SIDE=16, UNITS=5, WINDOW=False)
for kernel in (binning_kernels.tile_counts, binning_kernels.tile_keys):
    compile_for_sm90(kernel, PREPARE_OPTIONS, SIDE=16, BLOCK=binning_kernels.BLOCK)
for neural in (False, True):
    compile_for_sm90(statistics_kernels.accumulate, PREPARE_OPTIONS, NP=8 if neural else 1, NEURAL=neural,
                     BLOCK=statistics_kernels.BLOCK)
ptx = {}
for floats in ("*fp32", "*fp64"):   # (float64: the tests' dtype, which takes other branches of the kernels)
    for kernel in (prepare_kernels.sh_color_forward, prepare_kernels.sh_color_backward):
        ptx[kernel.fn.__name__, floats] = compile_for_sm90(kernel, PREPARE_OPTIONS, floats, COEFFS=16,
                                                           BLOCK=prepare_kernels.BLOCK).asm["ptx"]
    for kernel in (prepare_kernels.neural_prep_forward, prepare_kernels.neural_prep_backward):
        compile_for_sm90(kernel, PREPARE_OPTIONS, floats, NP=8, BLOCK=prepare_kernels.BLOCK)
    for kernel in (prepare_kernels.gaussian_prep_forward, prepare_kernels.gaussian_prep_backward,
                   prepare_kernels.neural_bounds):
        compile_for_sm90(kernel, PREPARE_OPTIONS, floats, BLOCK=prepare_kernels.BLOCK)
    for kernel in (loss_kernels.ssim_rows, loss_kernels.ssim_columns, loss_kernels.adjoint_rows,
                   loss_kernels.adjoint_columns):
        compile_for_sm90(kernel, PREPARE_OPTIONS, floats, BLOCK=loss_kernels.BLOCK)
    compile_for_sm90(positivity_kernels.project_nonnegative, PREPARE_OPTIONS, floats, UNITS=8,
                     BLOCK=positivity_kernels.BLOCK)
# a float literal held in a plain local is made a float32 scalar: a float64 kernel's SH constants
# must reach its PTX in full, never rounded to float32 (C0 and C3[1] of core/splat/sh.py, 64-bit hex)
ptx = ptx["sh_color_backward", "*fp64"]
full, rounded = ("0d3FD20DD750429B6D", "0d40071FF8E45CAD2D"), ("0d3FD20DD760000000", "0d40071FF8E0000000")
print("float64 constants:", all(h in ptx for h in full) and not any(h in ptx for h in rounded))
"""


@pytest.mark.skipif(torch.cuda.is_available(), reason="with a GPU the renders above compile and run the kernels")
def test_the_kernels_compile_for_a_gpu_without_one(tmp_path):
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    env["TRITON_CACHE_DIR"] = str(tmp_path / "cache")
    done = subprocess.run([sys.executable, "-c", COMPILE], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    # per kernel: its name, then ptxas's lines ("Used N registers", "B bytes spill stores, B bytes spill loads")
    kernels = done.stdout.split("kernel ")[1:]
    assert len(kernels) == 35, done.stdout
    assert "float64 constants: True" in done.stdout, done.stdout
    for log in kernels:
        spills = re.findall(r"(\d+) bytes spill stores, (\d+) bytes spill loads", log)
        registers = re.findall(r"Used (\d+) registers", log)
        assert spills and registers, log
        if "*fp32" in log.splitlines()[0]:   # the dtype training runs (float64: the tests', may spill)
            assert all(int(stores) == int(loads) == 0 for stores, loads in spills), log
