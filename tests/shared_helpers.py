"""Plain helpers that several test modules share (imported by name: pyproject.toml puts tests/ on
the path). Fixtures live in conftest.py."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from radfield.core import backends, kinds
from radfield.core.kinds import (DynamicGaussians, DynamicNeuralPrimitives, NeuralPrimitives, RelightGaussians,
                                  RelightNeuralPrimitives)
from radfield.core.kinds.dynamic import TEMPORAL_TERMS
from radfield.core.kinds.relight import init_network
from radfield.core.render.antialias import render_model
from radfield.core.render.rasterize import render
from radfield.errors import RadfieldError
from radfield.core.trainer.loop import make_strategy
from radfield.core.trainer.loop import initial_state, make_optimizer
from radfield.pipeline.config import load_config


# --- transforms.json files -----------------------------------------------------------------------

def frames(path: Path) -> list[dict]:
    return json.loads(path.read_text())["frames"]


def rewrite(path: Path, edit) -> None:
    """Apply edit(frames) to a transforms file's frames, in place."""
    meta = json.loads(path.read_text())
    edit(meta["frames"])
    path.write_text(json.dumps(meta))


def nerfstudio_copy(data: Path, root: Path) -> Path:
    """A nerfstudio transforms.json of a NeRF-synthetic folder's train frames (images copied beside it)."""
    shutil.copytree(data / "train", root / "images")
    meta = json.loads((data / "transforms_train.json").read_text())
    for frame in meta["frames"]:
        frame["file_path"] = frame["file_path"].replace("./train/", "images/") + ".png"
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


# --- models ----------------------------------------------------------------------------------------

def with_network(prims, seed=0, amplitude=0.4, hidden=8):
    """A relightable model of static `prims` with a random colour network of `hidden` units (output
    clearly non-zero, and within the colour's range at the default amplitude and width)."""
    n, dtype = len(prims), prims.means.dtype
    net = init_network(n, hidden, seed, dtype)
    g = torch.Generator().manual_seed(seed + 7)
    net["color_w2"] = torch.randn(n, 3, hidden, generator=g, dtype=dtype) * amplitude
    net["color_b2"] = torch.randn(n, 3, generator=g, dtype=dtype) * 0.1
    if isinstance(prims, NeuralPrimitives):
        return RelightNeuralPrimitives(**{k: getattr(prims, k) for k in ("means", "log_scales", "quats", "sh", "w1",
                                                                         "b1", "w2", "b2")},
                                       omega0=prims.omega0, window=prims.window, **net)
    return RelightGaussians(means=prims.means, log_scales=prims.log_scales, quats=prims.quats, sh=prims.sh,
                            opacities=prims.opacities, **net)


def with_time(prims, seed=0, omega=2 * math.pi):
    """A time-conditioned model of static `prims` (neural or Gaussian) whose temporal tensors are
    random (colour, and phases or opacity, change clearly over time) at time frequency `omega`."""
    g = torch.Generator().manual_seed(seed)
    n, dtype = len(prims), prims.means.dtype
    if isinstance(prims, NeuralPrimitives):
        fields = {k: getattr(prims, k) for k in ("means", "log_scales", "quats", "sh", "w1", "b1", "w2", "b2")}
        return DynamicNeuralPrimitives(**fields, omega0=prims.omega0, window=prims.window, time_frequency=omega,
                                       w_t=(torch.rand(n, prims.hidden, generator=g, dtype=dtype) * 2 - 1) * 0.1,
                                       sh_t=torch.randn(n, TEMPORAL_TERMS, 3, generator=g, dtype=dtype) * 0.3)
    return DynamicGaussians(**{k: getattr(prims, k) for k in ("means", "log_scales", "quats", "sh", "opacities")},
                            time_frequency=omega, sh_t=torch.randn(n, TEMPORAL_TERMS, 3, generator=g, dtype=dtype) * 0.3,
                            opacity_t=torch.randn(n, TEMPORAL_TERMS, generator=g, dtype=dtype) * 0.5)


def drawn(model, camera) -> np.ndarray:
    """What `radfield render` writes for `camera` (a model file: the default background and near)."""
    config = load_config(None)
    with torch.no_grad():
        color = render_model(model, camera, background=tuple(config["data"]["background"]),
                             near=config["render"]["near"]).color
    return color.clamp(0, 1).numpy()


def refine_everything(prims, kind: str, densify: dict) -> tuple[dict, dict, dict]:
    """One refinement of `prims` by its kind's strategy with every primitive qualifying (all grown:
    cloned or split): (the parameters after, a copy of those before, the strategy's report)."""
    state = initial_state(prims, 1)
    assert set(kinds.get(kind).own_params) <= set(state.params)
    params = {n: t.clone().requires_grad_(True) for n, t in state.params.items()}
    rates = {k: 1e-3 for k in ("means", "log_scales", "quats", "sh_dc", "sh_rest", "mlp", "color", "opacities")}
    optimizer = make_optimizer(params, rates, 1.0, kind)
    strategy = make_strategy(kind, densify, extent=1.0, near=0.05, max_primitives=None, initial_count=len(prims),
                             attrs=kinds.get(kind).attrs(prims))
    acc = strategy.init_state(len(prims), "cpu")
    acc["grad"][:] = torch.linspace(0, 1, len(prims)) + 1.0   # every primitive qualifies
    acc["count"][:] = 1.0
    before = {n: t.detach().clone() for n, t in params.items()}
    report = strategy.refine(acc, params, optimizer, densify["every"], torch.Generator().manual_seed(0))
    assert report["cloned"] + report["split"] > 0 and len(params["means"]) > len(prims)
    return params, before, report


# --- whole renders and their gradients, compared between backends ---------------------------------

# float32 against float64 on the same (float32-rounded) inputs: colour, alpha and depth absolute,
# gradients relative to the view's largest (they are sums over the view)
TOL32 = dict(rtol=1e-3, atol=1e-4)


def render_with_grads(prims, cam, backend: str):
    """The render on `backend` alone (as kernels of its own: the seam must choose it), and the
    gradients of a fixed random weighting of its image, alpha and depth w.r.t. every tensor of prims."""
    with backends.using(backend):
        assert backends.select(prims.means.device, prims.means.dtype, kinds.of(prims).name) == backend
        params = prims.map(lambda t: t.clone().requires_grad_(True))
        out = render(params, cam, background=(0.2, 0.3, 0.4), near=0.05)
        g = torch.Generator().manual_seed(0)
        weights = [torch.randn(t.shape, generator=g, dtype=torch.float64).to(t) for t in (out.color, out.alpha, out.depth)]
        loss = sum((w * t).sum() for w, t in zip(weights, (out.color, out.alpha, out.depth)))
        names = list(params.tensors())
        grads = torch.autograd.grad(loss, [params.tensors()[n] for n in names])
    return out, dict(zip(names, grads))


def assert_renders_close(out, grads, reference, reference_grads, tol, what: str = "") -> None:
    """Images and every gradient of one render within `tol` of another's (gradients relative to the
    reference's largest, at least 1)."""
    for name in ("color", "alpha", "depth"):
        torch.testing.assert_close(getattr(out, name).to(getattr(reference, name)), getattr(reference, name), **tol,
                                   msg=lambda m: f"{what}{name}: {m}")
    assert grads.keys() == reference_grads.keys()
    for name, ref in reference_grads.items():
        scale = ref.abs().max().clamp_min(1.0)
        torch.testing.assert_close(grads[name].to(ref) / scale, ref / scale, **tol, msg=lambda m: f"{what}d/d{name}: {m}")


def float64_twin(prims, cam):
    """The reference of a float32 render: the torch twin in float64 on the same float32-rounded
    inputs. A float32 path is compared with it, not with another float32 path: two float32
    paths round differently (and differently on AVX-512 and AVX2 CPUs, whose MKL and Sleef
    round some functions to another last bit), so their difference says little about either."""
    return render_with_grads(prims.to(dtype=torch.float64), cam, backends.TORCH)


def float32_sensitivity(prims, cam, ulps: float = 4.0, draws: int = 4) -> float:
    """How far the float64 twin's image and gradients move (absolute; gradients relative to the
    largest, at least 1) when every parameter moves by up to `ulps` float32 ulps: what any float32
    evaluation of the scene may be off by in the worst case, whatever its care. A scene with a
    kink of the gradient at one of its pairs (an entry exactly at the near plane, a sphere's tied
    max(s), α at the clamp) has a sensitivity near 1: no float32 bound can hold there on every CPU."""
    base, base_grads = float64_twin(prims, cam)
    worst = 0.0
    for draw in range(draws):
        g = torch.Generator().manual_seed(100 + draw)
        moved = prims.to(dtype=torch.float64).map(
            lambda t: t * (1 + ulps * 2.0**-24 * (2 * torch.rand(t.shape, generator=g, dtype=t.dtype) - 1).to(t.device)))
        out, grads = render_with_grads(moved, cam, backends.TORCH)
        for name in ("color", "alpha", "depth"):
            worst = max(worst, float((getattr(out, name) - getattr(base, name)).detach().abs().max()))
        for name, ref in base_grads.items():
            worst = max(worst, float((grads[name] - ref).abs().max() / ref.abs().max().clamp_min(1.0)))
    return worst


# --- the non-negative density projection ---------------------------------------------------------

def projection_rows(width: int, dtype, generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(W2 (300, width), b2 (300,), mask (300,)) for the projection's kernels against the twin: ties
    (rows 0-19), rows inside the cone (20-39), the polar cone (40-59), zeros (60-69), random rest;
    the mask sets about 80 % of the rows."""
    w2 = (torch.randn(300, width, generator=generator) * 0.4).to(dtype)
    b2 = (torch.randn(300, generator=generator) * 0.3).to(dtype)
    w2[:20] = 0.25                                # ties
    b2[20:40] = w2[20:40].abs().sum(-1) + 0.1     # inside the cone
    b2[40:60] = -w2[40:60].abs().amax(-1) - 0.1   # the polar cone
    w2[60:70], b2[60:70] = 0.0, 0.0
    return w2, b2, torch.rand(300, generator=generator) < 0.8


def one_line_error(call) -> str:
    """The message of the RadfieldError that `call()` raises, checked to be one line."""
    with pytest.raises(RadfieldError) as info:
        call()
    message = str(info.value)
    assert message and "\n" not in message, message
    return message
