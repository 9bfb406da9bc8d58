"""The primitive-kind registry (radfield.core.kinds) is the one seam a new kind plugs into.

The test defines a kind of its own — constant-density ellipsoids, α = 1 − exp(−σ · chord) with σ
= exp(log_density) per unit of the primitive's size max(s), the chord through the ellipsoid from
ray_ellipsoid —
registers it, and trains, checkpoints, saves, loads, renders, deforms with a cage and exports it
through the project's own code paths, none of which is touched. And the registry refuses what it
does not know, in one line.
"""

import math
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from radfield.core import backends, kinds
from radfield.core.geometry.cameras import Camera, look_at
from radfield.core.kinds import Gaussians, PrimitiveKind, Primitives, random_gaussians, random_neural
from radfield.core.splat.view import camera_directions, ellipsoid_bounds
from radfield.core.splat.kernels import alpha_from_optical_depth, ellipsoid_frame, ray_ellipsoid
from radfield.core.render.rasterize import render
from radfield.core.splat.sh import rgb_to_sh_dc
from radfield.core.trainer.loop import load_checkpoint, mean_psnr, save_checkpoint, train
from radfield.delivery.export import Content, export
from radfield.model_formats.ply_3dgs import read_gaussian_ply
from radfield.model_file import load_model, save_model
from radfield.edit.affine import deform_field
from radfield.edit.field import Field, box_cage
from radfield.errors import RadfieldError
from radfield.pipeline.config import load_config, load_defaults

BG = (1.0, 1.0, 1.0)


@dataclass
class Ellipsoids(Primitives):
    """Ellipsoids B(μ, R, s) of constant density σ = exp(log_density) (per unit of max(s), so that a
    scene's normalisation leaves it unchanged, as kinds/base.py asks)."""

    log_density: torch.Tensor = None  # (P,)

    kind = "ellipsoid"


def chord_alpha(u, v, intrinsics, m_cam, o_ell, density, inv_smax):
    """α = 1 − exp(−σ ℓ / max(s)) of each primitive (P,) over image points (P, A), ℓ the chord of
    the ray through the ellipsoid beyond the near plane."""
    d, l_near = camera_directions(u, v, intrinsics)
    l_in, l_out, hit = ray_ellipsoid(o_ell[:, None, :], d @ m_cam.transpose(1, 2))
    chord = torch.where(hit, torch.clamp_min(l_out - torch.maximum(l_in, l_near), 0.0), torch.zeros_like(l_out))
    return alpha_from_optical_depth((density * inv_smax)[:, None] * chord)


class EllipsoidKind(PrimitiveKind):
    name = "ellipsoid"
    primitives = Ellipsoids
    own_params = {"log_density": ()}
    lr_keys = {"log_density": "opacities"}   # train.lr has no key of its own for it

    def twin_view(self, prims, frame):
        bounds, visible = ellipsoid_bounds(prims, frame)
        m, smax = ellipsoid_frame(prims.means, prims.log_scales, prims.quats)
        o_ell = (m * (frame.campos - prims.means)[:, None, :]).sum(-1)
        return bounds, visible, (m @ frame.c2w[:3, :3], o_ell, torch.exp(prims.log_density), 1.0 / smax)

    def pair_kernel(self, prims):
        return chord_alpha

    def to_gaussians(self, prims, components=1):
        """A uniform ball has per-axis variance r²/5; the opacity is the central chord's along the mean radius."""
        scales = prims.scales
        alpha = -torch.expm1(-torch.exp(prims.log_density) * 2.0 * scales.mean(-1) / scales.amax(-1))
        return Gaussians(means=prims.means, log_scales=prims.log_scales - 0.5 * math.log(5.0), quats=prims.quats,
                         sh=prims.sh, opacities=torch.logit(alpha.clamp(1e-4, 0.99)))


@pytest.fixture
def ellipsoid():
    kind = kinds.register(EllipsoidKind())
    yield kind
    kinds.unregister(kind.name)


def ellipsoids(num=6, density=1.0, seed=0, colour=None):
    g = torch.Generator().manual_seed(seed)
    rgb = torch.rand(num, 3, generator=g)
    rgb = rgb if colour is None else torch.tensor(colour).expand(num, 3)   # the same geometry either way
    return Ellipsoids(means=(torch.rand(num, 3, generator=g) - 0.5) * 0.8,
                      log_scales=torch.log(0.15 + 0.1 * torch.rand(num, 3, generator=g)),
                      quats=torch.randn(num, 4, generator=g), sh=rgb_to_sh_dc(rgb)[:, None, :],
                      log_density=torch.full((num,), math.log(density)))


def cameras(n=4, size=20):
    return [Camera(fx=30.0, fy=30.0, cx=size / 2, cy=size / 2, width=size, height=size,
                   c2w=look_at((2.4 * math.cos(a), 2.4 * math.sin(a), 0.7), (0.0, 0.0, 0.0)), name=f"c{k}")
            for k, a in enumerate(2 * math.pi * np.arange(n) / n)]


def test_the_registry_knows_the_built_in_kinds_and_refuses_others():
    assert kinds.names()[:2] == ("neural", "gaussian")
    assert kinds.of(random_neural(2)).name == "neural" and kinds.of(random_gaussians(2)).name == "gaussian"
    assert kinds.get("neural").retrainable_locally and kinds.get("gaussian").exact_gaussians
    with pytest.raises(RadfieldError, match="unknown primitive kind 'ellipsoid'"):
        kinds.get("ellipsoid")
    with pytest.raises(ValueError, match="registered already"):
        kinds.register(type(kinds.get("neural"))())


def test_the_declared_kinds_are_the_registered_ones(cli):
    """pyproject.toml's entry points (group radfield.kinds) declare every built-in kind, each the
    registered object, so `reconstruct --help` lists what the registry holds without importing it."""
    from importlib.metadata import entry_points

    from radfield.cli.common import kind_names

    points = {point.name: point for point in entry_points(group="radfield.kinds")}
    assert set(points) == set(kinds.names())
    assert all(points[name].load() is kinds.get(name) for name in points)
    code, out, _ = cli("reconstruct", "--help")
    assert code == 0 and f"Registered kinds: {', '.join(kind_names())}." in " ".join(out.split())


def test_a_kind_another_package_declares_is_loaded(monkeypatch, tmp_path):
    """An installed package's kind (its entry point) is registered when radfield's kinds load; one
    that fails to import is one warning, not a broken radfield."""
    import importlib.metadata
    import sys

    module = tmp_path / "plugin_kind.py"
    module.write_text("from radfield.core.kinds import NeuralPrimitives, register\n"
                      "from radfield.core.kinds.neural import NeuralKind\n"
                      "class PluginPrimitives(NeuralPrimitives):\n    kind = 'plugin-neural'\n"
                      "class PluginKind(NeuralKind):\n    name, primitives = 'plugin-neural', PluginPrimitives\n"
                      "KIND = register(PluginKind())\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    declared = [importlib.metadata.EntryPoint("plugin-neural", "plugin_kind:KIND", "radfield.kinds"),
                importlib.metadata.EntryPoint("broken", "no_such_module:KIND", "radfield.kinds")]
    monkeypatch.setattr(importlib.metadata, "entry_points", lambda group=None: declared if group == "radfield.kinds" else [])
    try:
        with pytest.warns(RuntimeWarning, match="the primitive kind 'broken' .* failed to load"):
            kinds._load_declared_kinds()
        assert "plugin-neural" in kinds.names() and "broken" not in kinds.names()
    finally:
        if "plugin-neural" in kinds.names():
            kinds.unregister("plugin-neural")
        sys.modules.pop("plugin_kind", None)


def test_a_new_kind_renders_through_the_torch_twin(ellipsoid):
    prims, cam = ellipsoids(), cameras(1)[0]
    assert "ellipsoid" in kinds.names() and kinds.of(prims) is ellipsoid
    # no backend has a whole-view renderer for it: the kind's own twin runs on every device
    assert backends.select("cpu", torch.float32, kind="ellipsoid") == backends.TORCH
    out = render(prims, cam, background=BG)
    assert out.meta["visible"] == 6 and out.meta["contributing_pairs"] > 50
    assert float(out.alpha.max()) > 0.5 and float(out.alpha.min()) == 0.0
    with backends.using(backends.TORCH):   # the colour too on the twin: the same image
        torch.testing.assert_close(render(prims, cam, background=BG).color, out.color, rtol=1e-6, atol=1e-6)


def test_a_new_kind_trains_checkpoints_saves_and_loads(ellipsoid, tmp_path):
    cams = cameras()
    truth = ellipsoids(seed=1)
    with torch.no_grad():
        images = torch.stack([render(truth, c, background=BG).color for c in cams])
    start = ellipsoids(seed=1, density=0.25, colour=[0.5, 0.5, 0.5])
    cfg = load_defaults()["train"]
    cfg.update(iterations=25, sh_degree=0, batch_views=1, checkpoint_every=100, eval_every=0)
    cfg["lr"] = {k: v * 10 for k, v in cfg["lr"].items()}   # a short run: a larger step
    log = []
    state = train(start, cams, images, cfg, background=BG, extent=1.0, seed=0, on_step=lambda s, info: log.append(info))
    losses = [info["loss"] for info in log]
    assert len(losses) == 25 and sum(losses[-5:]) < 0.6 * sum(losses[:5])
    trained = state.primitives()
    assert isinstance(trained, Ellipsoids) and len(trained) == 6   # its default strategy: a fixed population
    assert mean_psnr(trained, cams, images, background=BG) > mean_psnr(start, cams, images, background=BG) + 5

    save_checkpoint(tmp_path / "state.safetensors", state)
    back = load_checkpoint(tmp_path / "state.safetensors")
    assert back.kind == "ellipsoid" and back.attrs == {} and torch.equal(back.params["log_density"], state.params["log_density"])

    save_model(tmp_path / "model.safetensors", trained)
    loaded = load_model(tmp_path / "model.safetensors")
    assert isinstance(loaded, Ellipsoids)
    for name, t in trained.tensors().items():
        assert torch.equal(getattr(loaded, name), t), name
    torch.testing.assert_close(render(loaded, cams[0], background=BG).color, render(trained, cams[0], background=BG).color)


def test_a_new_kind_is_edited_with_a_cage_and_exported(ellipsoid, tmp_path):
    prims = ellipsoids()
    vertices, tets = box_cage([-1, -1, -1], [1, 1, 1], 2)
    fld = Field(prims, vertices, tets)
    fld.rebind()
    stretch = np.array([1.5, 1.0, 1.0])
    moved = deform_field(fld, vertices * stretch, split=None).prims   # one affine map: exact for every primitive
    assert isinstance(moved, Ellipsoids) and torch.equal(moved.log_density, prims.log_density)
    torch.testing.assert_close(moved.means, prims.means * torch.tensor(stretch, dtype=torch.float32), rtol=1e-5, atol=1e-6)
    assert (moved.scales.amax(-1) > prims.scales.amax(-1) * 1.01).all()
    assert render(moved, cameras(1)[0], background=BG).meta["visible"] == 6

    figures = export(Content(model=moved), "ply-3dgs", tmp_path / "moved.ply")
    assert figures == {"gaussians": 6, "bytes": (tmp_path / "moved.ply").stat().st_size, "from": "ellipsoid"}
    gaussians = read_gaussian_ply(tmp_path / "moved.ply")
    torch.testing.assert_close(gaussians.means, moved.means)
    torch.testing.assert_close(gaussians.log_scales, moved.log_scales - 0.5 * math.log(5.0))


def test_a_model_file_of_an_unknown_kind_is_refused_in_one_line(ellipsoid, tmp_path):
    save_model(tmp_path / "ellipsoids.safetensors", ellipsoids())
    assert isinstance(load_model(tmp_path / "ellipsoids.safetensors"), Ellipsoids)
    kinds.unregister("ellipsoid")
    with pytest.raises(RadfieldError) as error:
        load_model(tmp_path / "ellipsoids.safetensors")
    message = str(error.value)
    assert "\n" not in message and "metadata kind is 'ellipsoid', expected one of ['gaussian', 'gaussian-dynamic', 'gaussian-relight', 'neural', 'neural-dynamic', 'neural-relight']" in message

    meta = {"format": "radfield", "kind": "tetrahedra", "version": "1", "sh_degree": "0"}
    save_file({"means": torch.zeros(2, 3)}, str(tmp_path / "odd.safetensors"), metadata=meta)
    with pytest.raises(RadfieldError, match=r"metadata kind is 'tetrahedra', expected one of \['gaussian', 'gaussian-dynamic', 'gaussian-relight', 'neural', 'neural-dynamic', 'neural-relight'\]$"):
        load_model(tmp_path / "odd.safetensors")


def test_the_config_offers_the_registered_kinds(ellipsoid):
    assert load_config(sets=["train.primitive=ellipsoid"])["train"]["primitive"] == "ellipsoid"
    kinds.unregister("ellipsoid")
    with pytest.raises(RadfieldError, match='train.primitive must be one of neural, gaussian, neural-dynamic, gaussian-dynamic, neural-relight, gaussian-relight, got "ellipsoid"'):
        load_config(sets=["train.primitive=ellipsoid"])
