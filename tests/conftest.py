"""Fixtures and helpers shared by the test modules."""

import os
import sys
from pathlib import Path

import pytest
import torch
from torch.overrides import TorchFunctionMode

from radfield.cli.main import main

# the project's shared data, beside the worktree (/work/wt/shared -> /work/shared)
SHARED_DATASETS = Path(__file__).resolve().parents[2] / "shared" / "datasets"


def in_ci() -> bool:
    """Whether the tests run in CI (env CI=true), where a test may not skip what it checks."""
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


def shared_dataset(name: str, needs: str = "") -> Path:
    """The folder of ../shared/datasets/NAME (with its entry `needs`, e.g. "images", present).

    Missing: the test is skipped on a developer's machine, but FAILS under CI=true, so that CI
    cannot stay green by skipping the tests that need the data."""
    path = SHARED_DATASETS / name
    if not (path / needs).exists():
        message = f"shared dataset not found: {path / needs}"
        if in_ci():
            pytest.fail(f"{message} (CI=true: tests that need ../shared must not skip)", pytrace=False)
        pytest.skip(message)
    return path


@pytest.fixture(name="shared_dataset", scope="session")
def shared_dataset_fixture():
    """`shared_dataset(name, needs="")` for tests (see the function)."""
    return shared_dataset


@pytest.fixture(scope="session")
def fox() -> Path:
    """../shared/datasets/fox_small (photos in images/, nerfstudio poses with lens distortion)."""
    return shared_dataset("fox_small", "images")


def run_radfield(*args) -> int:
    """Run `radfield ARGS` in this process; its exit code."""
    argv = sys.argv
    sys.argv = ["radfield", *map(str, args)]
    try:
        main()
        return 0
    except SystemExit as exit_:
        return exit_.code or 0
    finally:
        sys.argv = argv


@pytest.fixture(name="run_radfield", scope="session")
def run_radfield_fixture():
    """`run_radfield(*args) -> exit code`: `radfield ARGS` in this process (for module fixtures,
    which cannot use `cli`)."""
    return run_radfield


@pytest.fixture
def cli(capsys):
    """Run `radfield ARGS` in this process: cli(*args) -> (exit code, stdout, stderr)."""

    def run(*args) -> tuple[int, str, str]:
        code = run_radfield(*args)
        out, err = capsys.readouterr()
        return code, out, err

    return run


class Killed(Exception):
    """Raised by `kill_and_resume`'s step hook: the training run is killed."""


def kill_and_resume(start, cameras, images, cfg, path, *, kill_at: int = 7, **run):
    """Train `start` with checkpoints written to `path`, kill the run after step `kill_at`, and
    resume it from its last checkpoint: (the checkpoint's state, the resumed run's final state)."""
    from radfield.core.trainer.loop import load_checkpoint, save_checkpoint, train

    def kill(step, info):
        if step == kill_at:
            raise Killed

    with pytest.raises(Killed):
        train(start, cameras, images, cfg, **run, on_step=kill, checkpoint=lambda s: save_checkpoint(path, s))
    saved = load_checkpoint(path)
    return saved, train(start, cameras, images, cfg, **run, start_state=saved)


@pytest.fixture(name="kill_and_resume")
def kill_and_resume_fixture():
    """`kill_and_resume(start, cameras, images, cfg, path, kill_at=7, **run)` (see the function)."""
    return kill_and_resume


# --- shared test scenes (builders are fixtures: under --import-mode=importlib a test module cannot
# import conftest; torch and the geometry libraries are imported inside, so that collecting a test
# that needs none of them imports none of them) -----------------------------------------------


def config_section(section: str, **overrides) -> dict:
    """A config section of pipeline.yaml with some keys changed."""
    from radfield.pipeline.config import load_defaults

    return {**load_defaults()[section], **overrides}


@pytest.fixture(name="cfg", scope="session")
def config_section_fixture():
    """`cfg(section, **overrides)`: a config section of pipeline.yaml with some keys changed."""
    return config_section


def torus_points(n, rng, R=1.0, r=0.35):
    """n points on the surface of a torus (ring radius R, tube radius r) about the z axis."""
    import numpy as np

    u, w = rng.uniform(0, 2 * np.pi, (2, n))
    return np.stack([(R + r * np.cos(w)) * np.cos(u), (R + r * np.cos(w)) * np.sin(u), r * np.sin(w)], 1)


@pytest.fixture(name="torus_points", scope="session")
def torus_points_fixture():
    """`torus_points(n, rng, R=1.0, r=0.35)` (see the function)."""
    return torus_points


@pytest.fixture(scope="session")
def torus_envelope():
    """Envelope of 3000 torus samples plus 40 floaters 2.5-3.5 from the centre: (the samples, the
    envelope's vertices, faces, figures). Built once (pymeshlab, seconds) for tests/test_envelope.py
    and tests/test_cage.py; treat it as read-only."""
    import numpy as np

    from radfield.core.geometry.envelope import build_envelope

    rng = np.random.default_rng(0)
    surface = torus_points(3000, rng)
    direction = rng.normal(size=(40, 3))
    floaters = direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(2.5, 3.5, (40, 1))
    v, f, figures = build_envelope(np.concatenate([surface, floaters]), config_section("envelope", target_faces=400))
    return surface, v, f, figures


RENDER_SIZE = 24, 20   # (width, height) of render_scene's camera


def render_scene(kind: str, dtype, hidden: int = 8):
    """A tiny view of 14 primitives of `kind` ("neural", "neural-window" or "gaussian") as
    (prims in `dtype`, camera): for neural primitives the camera inside one, one straddling the near
    plane, one at the α clamp; Gaussians scattered in front. The fused kernels' hard cases, for the
    backend and fused-kernel comparisons (tests/test_backends.py, tests/test_fused.py)."""
    import math

    import torch

    from radfield.core.geometry.cameras import Camera, look_at
    from radfield.core.kinds import random_gaussians, random_neural

    eye = torch.tensor([0.3, -3.0, 0.5])
    if kind in ("neural", "neural-window"):
        prims = random_neural(14, sh_degree=1, hidden=hidden, scale=0.35, extent=0.6, b2=2.0, w2_amplitude=1.0, seed=4)
        # not quite spheres: a sphere's max(s) is a three-way tie, where the gradient w.r.t. its
        # scales has a kink (as for an entry at the near plane, which the round sphere 1 had on one
        # pixel, 2e-9 from the plane): float32 then lands on either side (test_float32_scenes)
        prims.means[0], prims.b2[0] = eye + torch.tensor([0.05, 0.1, -0.05]), 0.3
        prims.log_scales[0] = math.log(0.4) + torch.tensor([0.0, 0.02, -0.015])
        prims.means[1] = eye + torch.tensor([0.0, 0.35, 0.0])
        prims.log_scales[1] = math.log(0.3) + torch.tensor([0.01, -0.012, 0.0])
        prims.b2[2] = 40.0
        prims.window = kind == "neural-window"
    else:
        prims = random_gaussians(14, sh_degree=1, scale=0.15, extent=0.6, seed=4)
    width, height = RENDER_SIZE
    cam = Camera(fx=30.0, fy=33.0, cx=12.3, cy=9.7, width=width, height=height,
                 c2w=look_at(tuple(eye.tolist()), (0, 0, 0)))
    return prims.to(dtype=dtype), cam


@pytest.fixture(name="render_scene", scope="session")
def render_scene_fixture():
    """`render_scene(kind, dtype, hidden=8) -> (prims, camera)` (see the function)."""
    return render_scene


def densify_config() -> dict:
    """A train.densify section for the strategy tests: every step from 1 counts, low thresholds."""
    return {"start": 1, "stop": 100, "every": 10, "grad_threshold": 1e-3, "grow_scale": 0.01, "prune_scale": 0.5,
            "prune_threshold": 1e-6, "gaussian": {"grad_threshold": 2e-4, "prune_scale": 0.1, "min_opacity": 0.005,
                                                   "opacity_reset_every": 3000}}


def strategy_scene(kind: str, dtype, p: int = 4000, seed: int = 0):
    """(params, grads, camera) for a view's densification statistics: p primitives whose means spread
    well beyond the frustum and whose scales run from tiny to large (both outcomes of the frustum
    test), the gradients of `kind`'s parameters, and a 64x48 camera looking at the middle."""
    import torch

    from radfield.core.geometry.cameras import Camera, look_at

    g = torch.Generator().manual_seed(seed)
    params = {"means": (torch.rand(p, 3, generator=g, dtype=dtype) * 2 - 1) * 3,
              "log_scales": torch.log(torch.rand(p, 3, generator=g, dtype=dtype) * 0.8 + 1e-3)}
    if kind == "gaussian":
        grads = {"means": torch.randn(p, 3, generator=g, dtype=dtype) * 1e-4}
    else:
        grads = {"w1": torch.randn(p, 8, 3, generator=g, dtype=dtype), "b1": torch.randn(p, 8, generator=g, dtype=dtype),
                 "w2": torch.randn(p, 8, generator=g, dtype=dtype), "b2": torch.randn(p, generator=g, dtype=dtype)}
    cam = Camera(50.0, 45.0, 31.0, 24.5, 64, 48, look_at((0.3, -3.5, 1.0), (0.0, 0.0, 0.2)))
    return params, grads, cam


@pytest.fixture(name="strategy_scene", scope="session")
def strategy_scene_fixture():
    """`strategy_scene(kind, dtype, p=4000, seed=0) -> (params, grads, camera)` (see the function)."""
    return strategy_scene


@pytest.fixture(name="densify_config", scope="session")
def densify_config_fixture():
    """`densify_config()`: a fresh train.densify section for the strategy tests (see the function)."""
    return densify_config


def hand_run(root: Path, half: float = 0.8):
    """(dataset, run, cage vertices, cage tets): a 24×24 blobs dataset and a run made by hand from 20
    random neural primitives with a box cage of half-size `half` and the binding, for the tests of
    commands that read a run (the reconstruction itself is not what they check)."""
    import json

    from radfield.core.geometry.cage import write_binding, write_cage
    from radfield.core.kinds import random_neural
    from radfield.demo.static import generate_scene
    from radfield.model_file import save_model
    from radfield.edit.field import box_cage

    data = generate_scene("blobs", root / "data", n_train=3, n_test=2, size=24, seed=0)
    run = root / "run"
    for stage in ("train", "tetra", "bind"):
        (run / stage).mkdir(parents=True)
    prims = random_neural(20, sh_degree=1, extent=0.4, scale=0.15, seed=2)
    save_model(run / "train" / "model.safetensors", prims)
    v, t = box_cage([-half] * 3, [half] * 3, 2)
    write_cage(run / "tetra", v, t)
    write_binding(run / "bind" / "model_binding.npz", prims.means.numpy(), run / "tetra" / "cage.npz")
    (run / "radfield-run.json").write_text(json.dumps({"kind": "radfield-run", "input": str(data)}))
    (run / "config.yaml").write_text("data:\n  background: [1, 1, 1]\n")
    return data, run, v, t


@pytest.fixture(name="hand_run", scope="session")
def hand_run_fixture():
    return hand_run


# --- reads of the device's values --------------------------------------------------------------

class HostReads(TorchFunctionMode):
    """Inside (`with HostReads(...) as reads`): every op of radfield's own code that makes the host
    wait for a tensor's value, in `reads.seen` as (reads.step, op, the function that called it). On
    a GPU each of them drains the device's queue, so the GPU idles while the host launches what
    follows; here CPU tensors stand in for the device's, so the ops are found by name: the reads
    (item, tolist, int(), bool(), cpu(), numpy()), and the ops whose result's size is a device
    value (nonzero, masked selection, unique, bincount, repeat_interleave without output_size,
    one-argument where). Code that works on host tensors by design (a camera's own checks, draws
    from CPU generators) is passed as `host_side`: nothing under those functions is counted. What
    this cannot see: blocking copies to the device (tests/test_cuda.py checks those on a GPU)."""

    READS = {"item", "tolist", "__int__", "__float__", "__bool__", "__index__", "cpu", "numpy", "nonzero", "argwhere",
             "masked_select", "unique", "unique_consecutive", "bincount", "repeat_interleave", "where"}
    LIBRARIES = ("torch", "triton", "numpy")   # their own frames between radfield's call and the op

    def __init__(self, host_side=()):
        super().__init__()
        self.step, self.seen = 0, []
        self.host_side = {function.__code__ for function in host_side}

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if self.waits(getattr(func, "__name__", ""), args, kwargs):
            caller = self.caller()
            if caller is not None:
                self.seen.append((self.step, func.__name__, caller))
        return func(*args, **kwargs)

    def waits(self, name: str, args, kwargs) -> bool:
        if name in ("__getitem__", "__setitem__", "index_put_"):
            index = args[1] if len(args) > 1 else None
            return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool
                       for i in (index if isinstance(index, tuple) else (index,)))
        if name == "repeat_interleave":
            return "output_size" not in kwargs
        if name == "where":
            return len(args) + len(kwargs) == 1
        return name in self.READS

    def caller(self) -> str | None:
        """radfield's function that asked ("module.function"), or None: a library's own work (the
        Triton interpreter's), or host-side code."""
        frame, asked = sys._getframe(2), None
        while frame is not None:
            if frame.f_code in self.host_side:
                return None
            module = frame.f_globals.get("__name__", "")
            if asked is None and module.split(".")[0] not in self.LIBRARIES:
                if module.split(".")[0] != "radfield":
                    return None
                asked = f"{module}.{frame.f_code.co_name}"
            frame = frame.f_back
        return asked


@pytest.fixture
def training_reads(monkeypatch):
    """HostReads over loop.train (`with training_reads: train(...)`), each read with the optimiser
    step being run (`step`: from 1; 0 is the set-up before the first). Host-side by design: the
    view order and the ray jitter (draws from CPU generators) and the checks of the jittered
    cameras they make."""
    from radfield.core.geometry.cameras import Camera
    from radfield.core.render.antialias import jitter_offsets
    from radfield.core.trainer import loop

    reads = HostReads(host_side=(loop.views_for_step, jitter_offsets, Camera.__post_init__))
    decayed = loop.decayed

    def step_marker(lr, ratio, step, iterations):   # the first thing each step does
        reads.step = step + 1
        return decayed(lr, ratio, step, iterations)

    monkeypatch.setattr(loop, "decayed", step_marker)
    return reads
