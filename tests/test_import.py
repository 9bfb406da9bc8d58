"""`radfield import` (issue 41): a model from elsewhere as a run with a cage of its own, and the
commands that take a foreign model file directly.

The fixture is real: a Gaussian reconstruction of `demo-scene objects` (with its own cage),
exported as a 3DGS PLY, imported. Edits of the import through its built cage are scored, as
tests/test_edit_truth.py scores edits, against the renders of the truly twisted shapes, beside the
same edit of the original run: within 1 dB of it. The boolean difference cuts both alike.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from radfield import model_formats
from radfield.bench.render import bench_models
from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.core.kinds import random_gaussians
from radfield.core.render.antialias import render_model
from radfield.datasets.readers import load_dataset
from radfield.demo.static import generate_scene
from radfield.edit.boolean.gaussian_cut import halves, refine_boundary
from radfield.edit.boolean.shapes import parse_shape
from radfield.edit.source import load_source
from radfield.model_file import save_model

SIZE, TRAIN, TEST = 48, 24, 4


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10 * torch.log10(((a.double() - b.double()) ** 2).mean().clamp_min(1e-20)))


def renders(prims, cameras, background=(1.0, 1.0, 1.0)) -> list:
    with torch.no_grad():
        return [render_model(prims, camera, background=background) for camera in cameras]


def mean_psnr(a: list, b: list, what: str = "color") -> float:
    return float(np.mean([psnr(getattr(x, what), getattr(y, what)) for x, y in zip(a, b)]))


@pytest.fixture(scope="module")
def imported(tmp_path_factory, run_radfield) -> dict[str, Path]:
    """{"rest", "twist": datasets, "original": a Gaussian run of rest, "ply": its export,
    "run": the PLY imported}."""
    root = tmp_path_factory.mktemp("import")
    rest = generate_scene("objects", root / "rest", n_train=TRAIN, n_test=TEST, size=SIZE, mesh=False)
    twist = generate_scene("objects", root / "twist", n_train=TRAIN, n_test=TEST, size=SIZE, mesh=False, deform="twist")
    original = root / "original"
    assert run_radfield("reconstruct", rest, "-o", original, "--primitive", "gaussian", "--iterations", "300",
                        "--set", "stages=[sfm,data,triangulate,envelope,tetra,init,train,bind]", "-q") == 0
    ply = root / "model.ply"
    assert run_radfield("export", original, "-f", "ply-3dgs", "-o", ply, "-q") == 0
    assert run_radfield("import", ply, "-o", root / "run", "--views", "24", "--size", "64", "-q") == 0
    return {"rest": rest, "twist": twist, "original": original, "ply": ply, "run": root / "run", "root": root}


def test_an_imported_run_says_where_it_came_from_and_renders_its_model(imported, cli):
    run = imported["run"]
    code, out, _ = cli("info", run, "--json")
    info = json.loads(out)
    record = info["imported_from"]
    assert code == 0 and record["source"] == str(imported["ply"].resolve()) and record["format"] == "ply-3dgs"
    assert record["kind"] == "gaussian" and record["views"] == 24 and record["size"] == 64
    assert info["stages"]["tetra"]["tets"] > 100 and info["stages"]["bind"]["bound"] == record["primitives"]
    assert info["stages"]["envelope"]["source"] == "hull"
    # the model is the file's, exactly, and its renders are the run's dataset (16-bit PNGs)
    original = load_source(imported["original"]).prims
    model = load_source(run).prims
    assert torch.equal(model.means, original.means) and torch.equal(model.opacities, original.opacities)
    code, out, err = cli("eval", run, "-o", imported["root"] / "eval-self", "-q")
    assert code == 0, err
    assert float(out.split("PSNR ")[1].split(" dB")[0]) > 80.0, out
    # against the real photos the import scores what the original scores
    code, out_import, _ = cli("eval", run, "-d", imported["rest"], "-o", imported["root"] / "eval-import", "-q")
    code2, out_original, _ = cli("eval", imported["original"], "-o", imported["root"] / "eval-original", "-q")
    assert code == code2 == 0 and out_import.split("PSNR")[1][:9] == out_original.split("PSNR")[1][:9]


def test_edits_through_the_built_cage_land_as_the_original_s(imported, cli):
    """A twist (the closed-form map; and through the cage, smooth interpolation) and a boolean
    difference of the import against the same edit of the original run: the twist scored against
    the truly twisted shapes (within 1 dB of the original's score), the cut directly."""
    root, truth = imported["root"], load_dataset(imported["twist"], split="test")
    specs = {"twist": "- twist: {axis: z, degrees_per_unit: 45}",
             "twist-cage": "- twist: {axis: z, degrees_per_unit: 45, gradient: smooth}",
             "cut": "- boolean: {op: difference, shape: {sphere: {center: [0.3, 0.0, 0.3], radius: 0.4}}}"}
    scores = {}
    for name, entry in specs.items():
        spec = root / f"{name}.yaml"
        spec.write_text(f"operations:\n{entry}\n")
        for source in ("original", "run"):
            code, _, err = cli("edit", imported[source], "-s", spec, "-o", root / f"{name}-{source}", "-q")
            assert code == 0, err
        edited = {source: renders(load_source(root / f"{name}-{source}").prims, truth.cameras)
                  for source in ("original", "run")}
        if name.startswith("twist"):
            gt = [type("T", (), {"alpha": truth.load_image(k)[1]}) for k in range(len(truth))]
            scores[name] = {source: mean_psnr(images, gt, "alpha") for source, images in edited.items()}
        scores[name + " vs original"] = mean_psnr(edited["run"], edited["original"])
    print(scores)
    for name in ("twist", "twist-cage"):
        assert scores[name]["original"] > 15.0, scores   # a real reconstruction, really twisted
        assert abs(scores[name]["run"] - scores[name]["original"]) <= 1.0, scores
    assert scores["cut vs original"] > 60.0, scores      # the cut does not depend on the cage
    cut = load_source(root / "cut-run")
    assert len(cut.prims) != len(load_source(imported["run"]).prims) and (cut.tet >= 0).all()


def test_commands_take_a_foreign_model_file_directly(imported, cli, tmp_path):
    ply = imported["ply"]
    code, out, err = cli("render", ply, "-d", imported["rest"], "-o", tmp_path / "frames", "-q")
    assert code == 0 and len(list((tmp_path / "frames").glob("*.png"))) == TEST, err
    code, _, err = cli("export", ply, "-f", "spz", "-o", tmp_path / "m.spz", "-q")
    assert code == 0, err
    code, out, err = cli("eval", tmp_path / "m.spz", "-d", imported["rest"], "-o", tmp_path / "eval", "-q")
    assert code == 0 and "PSNR" in out, err
    code, _, err = cli("edit", tmp_path / "m.spz", "--translate", "0.1,0,0", "-o", tmp_path / "moved", "-q")
    assert code == 0, err
    moved, source = load_source(tmp_path / "moved").prims, model_formats.read(tmp_path / "m.spz")
    assert torch.allclose(moved.means, source.means + torch.tensor([0.1, 0.0, 0.0]), atol=1e-6)
    code, _, err = cli("export", tmp_path / "m.spz", "-f", "web", "-o", tmp_path / "site", "-q")
    assert code == 0 and (tmp_path / "site" / "index.html").is_file(), err


def test_import_refuses_what_it_cannot_take_and_leaves_nothing(imported, cli, tmp_path):
    dynamic = tmp_path / "dynamic.safetensors"
    save_model(dynamic, bench_models(20, ("neural-dynamic",))["neural-dynamic"])
    damaged = tmp_path / "damaged.ply"
    damaged.write_bytes(imported["ply"].read_bytes()[:5000])
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "keep.txt").write_text("mine")
    cases = [(dynamic, tmp_path / "a", "takes static models"), (damaged, tmp_path / "b", "damaged.ply"),
             (imported["ply"], busy, "not empty"), (tmp_path / "missing.ply", tmp_path / "c", "no such model file"),
             (imported["ply"], imported["run"], "is a radfield run directory")]
    for model, output, message in cases:
        code, out, err = cli("import", model, "-o", output, "-q")
        assert code != 0 and message in err and len(err.strip().splitlines()) == 1, err
        assert "Traceback" not in err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    assert [p.name for p in busy.iterdir()] == ["keep.txt"]
    code, _, err = cli("import", imported["ply"], "-o", tmp_path / "d", "--size", "3", "-q")
    assert code != 0 and "--size" in err and not (tmp_path / "d").exists()


# --- the Gaussian boundary split (edit/boolean/gaussian_cut.py) -------------------------------------

def test_a_split_keeps_the_moments_and_the_opacity_integral_along_the_axis():
    g = random_gaussians(50, sh_degree=1, seed=3).to(dtype=torch.float64)
    g.opacities = torch.full_like(g.opacities, -1.0)          # o ≈ 0.27: the pair's o' stays below the clamp
    h = halves(g)
    a, b = h.select(torch.arange(50)), h.select(torch.arange(50, 100))
    assert torch.allclose((a.means + b.means) / 2, g.means)
    cov = lambda p: (quat_to_rotmat(p.quats) * torch.exp(2 * p.log_scales)[:, None, :]) @ quat_to_rotmat(p.quats).transpose(1, 2)
    offset = (a.means - g.means)[..., None]
    mixture = (cov(a) + cov(b)) / 2 + offset @ offset.transpose(1, 2)   # the pair's second moment about the mean
    assert torch.allclose(mixture, cov(g), atol=1e-12)
    axis = g.log_scales.argmax(-1)
    rows = torch.arange(50)
    # ∫ o exp(−x²/2σ²) dx along the axis: the parent's and the pair's sum
    integral = lambda p: torch.sigmoid(p.opacities) * torch.exp(p.log_scales[rows, axis]) * math.sqrt(2 * math.pi)
    assert torch.allclose(integral(a) + integral(b), integral(g))


def test_a_half_space_cut_keeps_only_the_kept_side_and_thins_the_boundary():
    torch.manual_seed(0)
    g = random_gaussians(200, sh_degree=0, extent=0.5, scale=0.1, seed=4).to(dtype=torch.float64)
    shape = parse_shape({"halfspace": {"point": [0, 0, 0], "normal": [1, 0, 0]}}, "test")
    keep = lambda points: ~shape.inside(points)
    out, figures = refine_boundary(g, keep, shape, keep_inside=False)
    centres = out.means.numpy()
    assert (centres[:, 0] <= 0).all() and figures["splits"] > 0
    # what is kept reaches the plane to within the split Gaussians' size: at most 3σ over it
    reach = 3 * torch.exp(out.log_scales).amax(-1).numpy()
    assert (centres[:, 0] + reach > 0).any()
    assert np.median(reach[centres[:, 0] + reach > 0]) < np.median(3 * torch.exp(g.log_scales).amax(-1).numpy())
