"""The data, init and eval stages, the stage registry and the CLI around them, on a tiny
generated scene (6 train + 2 test views of 24×24 pixels)."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from radfield.errors import RadfieldError
from radfield.model_file import load_model, save_model
from radfield.core.kinds.neural_density import neural_line_integral
from radfield.core.kinds.neural_density import density_window
from radfield.core.kinds import neural
from radfield.core.trainer.loop import load_checkpoint, save_checkpoint
from radfield.datasets.images import read_image, write_image
from radfield.datasets.readers import load_dataset
from radfield.demo.static import generate_scene
from radfield.datasets import scene as data
from radfield.stages import init
from radfield.pipeline.config import load_config
from radfield.evaluation.evaluate import evaluate
from radfield.stages.train import MODEL_FILE
from radfield.pipeline.runner import Stage, read_manifest, run_pipeline
from radfield.stages.registry import stages

METRIC_KEYS = {"split", "kind", "psnr", "ssim", "num_primitives", "num_params", "file_size_bytes", "fps", "views",
               "width", "height", "per_view",
               "lpips", "lpips_note"}  # LPIPS is null on these 24×24 views (below AlexNet's 31×31), and says so


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    return generate_scene("blobs", tmp_path_factory.mktemp("data") / "blobs", n_train=6, n_test=2, size=24)


@pytest.fixture
def scene_copy(scene_dir, tmp_path) -> Path:
    return Path(shutil.copytree(scene_dir, tmp_path / "blobs"))


def config(*sets: str) -> dict:
    return load_config(sets=["init.num_points=200", "envelope.target_faces=200", *sets])


def run_until(stage: str, scene: Path, run_dir: Path, cfg: dict | None = None, pipeline=None) -> dict[str, str]:
    return run_pipeline(pipeline or stages(), run_dir, cfg or config(), input_path=scene, until_stage=stage, quiet=True)


def snapshot(folder: Path) -> dict[str, tuple[int, bytes]]:
    return {str(p.relative_to(folder)): (p.stat().st_mtime_ns, p.read_bytes())
            for p in sorted(folder.rglob("*")) if p.is_file()}


# --- data -----------------------------------------------------------------------------------------


def test_data_stage_describes_the_dataset(scene_dir, tmp_path):
    run_dir = tmp_path / "run"
    status = run_until("data", scene_dir, run_dir, config("data.downscale=2", "data.background=[0,0,0]"))
    assert status == {"sfm": "not applicable", "data": "ran"}
    figures = read_manifest(run_dir / "data")["figures"]
    assert figures | {"format": None} == {"images": 8, "train_images": 6, "test_images": 2, "width": 12, "height": 12,
                                          "points": 0, "format": None}
    description = json.loads((run_dir / "data" / data.SCENE).read_text())
    assert description["format"] == "nerf_synthetic" and description["posed"] is True
    assert description["root"] == str(scene_dir.resolve()) and description["background"] == [0, 0, 0]
    view = description["splits"]["train"][1]
    assert set(view) == {"name", "image", "fx", "fy", "cx", "cy", "width", "height", "c2w", "file_width",
                         "file_height", "distortion"}
    expected = load_dataset(scene_dir, "train", downscale=2).cameras[1]
    assert (view["name"], view["width"], view["fx"], view["cx"]) == (expected.name, 12, expected.fx, expected.cx)
    assert np.allclose(view["c2w"], expected.c2w.numpy()) and Path(view["image"]).is_file()

    scene = data.load_scene(run_dir / "data" / data.SCENE)
    assert [c.name for c in scene.test_cameras] == [c.name for c in load_dataset(scene_dir, "test").cameras]
    first = scene.train_cameras[0]
    expected = load_dataset(scene_dir, "train", downscale=2).cameras[0]
    assert (first.name, first.width, first.fx, first.cy) == (expected.name, 12, expected.fx, expected.cy)
    assert torch.equal(first.c2w, expected.c2w)
    images = scene.train_images()
    assert images.shape == (6, 12, 12, 3) and images.dtype == torch.float32
    assert torch.equal(images, load_dataset(scene_dir, "train", 2, (0, 0, 0)).load_images()[0])
    with np.load(run_dir / "data" / data.POINTS) as points:
        assert points["xyz"].shape == (0, 3) and points["rgb"].shape == (0, 3)
        assert len(points["mesh_vertices"]) == len(points["mesh_rgb"]) > 100
        assert points["mesh_faces"].shape[1] == 3 and points["mesh_faces"].max() < len(points["mesh_vertices"])


def test_normalisation(scene_dir, tmp_path):
    scene = data.scene_from_json(data.read_dataset(scene_dir, config()["data"])[0], scene_dir)
    norm = scene.normalization
    # the orbit cameras look at the origin: that is the centre, not the mean of the cameras
    assert torch.allclose(norm.center, torch.zeros(3, dtype=torch.float64), atol=1e-6)
    radii = torch.stack([norm.camera(c).center for c in scene.train_cameras]).norm(dim=1)
    assert radii.max() == pytest.approx(1.0) and scene.extent == pytest.approx(1.1 / norm.scale)
    points = torch.randn(50, 3, dtype=torch.float64) * 3
    assert torch.allclose(norm.invert(norm.apply(points)), points)
    camera = scene.test_cameras[0]
    assert torch.allclose(norm.invert(norm.camera(camera).center), camera.center)
    assert torch.equal(norm.camera(camera).c2w[:3, :3], camera.c2w[:3, :3])


def write_nerfstudio(folder: Path, scene_dir: Path, **extra) -> Path:
    """A nerfstudio transforms.json over the generated scene's train images."""
    meta = json.loads((scene_dir / "transforms_train.json").read_text())
    for frame in meta["frames"]:
        frame["file_path"] = str(scene_dir / f"{frame['file_path']}.png")
    folder.mkdir()
    (folder / "transforms.json").write_text(json.dumps(meta | extra))
    return folder


def test_val_every_carves_a_validation_split_out_of_the_training_views(scene_dir, tmp_path):
    native = data.read_dataset(scene_dir, config("data.val_every=3")["data"])[0]["splits"]
    train = [v["name"] for v in data.read_dataset(scene_dir, config()["data"])[0]["splits"]["train"]]
    assert [v["name"] for v in native["val"]] == train[2::3]
    assert [v["name"] for v in native["train"]] == [n for k, n in enumerate(train) if (k + 1) % 3]
    assert "val" not in data.read_dataset(scene_dir, config()["data"])[0]["splits"]
    # what `radfield render`/`eval` read back is the same split
    for split in ("train", "val"):
        again = data.load_split(scene_dir, split, config("data.val_every=3")["data"])
        assert [v.image_path.stem for v in again.views] == [v["name"] for v in native[split]]
    listed = data.read_dataset(write_nerfstudio(tmp_path / "every", scene_dir), config("data.test_every=3",
                                                                                       "data.val_every=2")["data"])[0]
    assert [v["name"] for v in listed["splits"]["val"]] == ["r_2", "r_5"]
    with pytest.raises(RadfieldError, match="val_every=1 leaves no training"):
        data.read_dataset(scene_dir, config("data.val_every=1")["data"])


def test_splits(scene_dir, tmp_path):
    described = data.read_dataset(write_nerfstudio(tmp_path / "every", scene_dir), config("data.test_every=3")["data"])
    assert [v["name"] for v in described[0]["splits"]["test"]] == ["r_0", "r_3"]
    assert [v["name"] for v in described[0]["splits"]["train"]] == ["r_1", "r_2", "r_4", "r_5"]
    listed = write_nerfstudio(tmp_path / "listed", scene_dir, train_filenames=[str(scene_dir / "train/r_5.png")],
                              test_filenames=[str(scene_dir / "train/r_1.png")])
    splits = data.read_dataset(listed, config()["data"])[0]["splits"]
    assert {name: [v["name"] for v in views] for name, views in splits.items()} == {"train": ["r_5"], "test": ["r_1"]}


def test_unposed_photos_are_recorded(scene_dir, tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    for path in sorted((scene_dir / "train").glob("r_?.png")):
        shutil.copy(path, photos / path.name)
    described, points = data.read_dataset(photos, config()["data"])
    assert described["posed"] is False and described["normalization"] is None
    assert len(described["splits"]["test"]) == 1 and len(points["xyz"]) == 0
    assert set(described["splits"]["train"][0]) == {"name", "image", "width", "height", "file_width", "file_height"}
    with pytest.raises(RadfieldError, match="no camera poses"):
        data.scene_from_json(described, photos).train_cameras


def break_missing_image(root: Path) -> str:
    (root / "test" / "r_1.png").unlink()
    return "r_1"


def break_json(root: Path) -> str:
    (root / "transforms_train.json").write_text('{"camera_angle_x": 0.7, "frames": [')
    return "transforms_train.json"


def break_size(root: Path) -> str:
    write_image(root / "train" / "r_4.png", np.zeros((10, 10, 4), np.float32))
    return "r_4.png"


@pytest.mark.parametrize("damage", [break_missing_image, break_json, break_size])
def test_dataset_errors_fail_first_and_leave_the_run_alone(scene_copy, tmp_path, cli, damage):
    run_dir = tmp_path / "run"
    assert cli("reconstruct", scene_copy, "-o", run_dir, "--until", "data", "-q")[0] == 0
    before = snapshot(run_dir)
    culprit = damage(scene_copy)
    code, out, err = cli("reconstruct", scene_copy, "-o", run_dir, "-q", "--set", "train.iterations=1")
    assert code == 1 and out == ""
    assert len(err.strip().splitlines()) == 1 and culprit in err, err
    assert snapshot(run_dir) == before


@pytest.mark.parametrize("args, named", [
    (["--set", "train.iteratons=5"], "train.iterations"),  # with a suggestion
    (["--set", "init.source=bogus"], "init.source"),
    (["--set", "init.neural_radius=-1"], "init.neural_radius"),
    (["--max-primitives", "0"], "--max-primitives must be at least 1, got 0"),   # a flag names itself
    (["--primitive", "splat"], "--primitive must be one of neural, gaussian"),
    (["--set", "data.test_every=1"], "data.test_every"),
    (["--downscale", "0"], "--downscale must be at least 1, got 0"),
    (["--set", "init.source=points"], "init.source"),  # the scene has no SfM points
    (["--set", "eval.split=val"], "eval.split"),  # nor a val split
])
def test_config_errors_name_the_key_or_the_flag(scene_dir, tmp_path, cli, args, named):
    code, out, err = cli("reconstruct", scene_dir, "-o", tmp_path / "run", *args)
    assert code == 1 and len(err.strip().splitlines()) == 1 and named in err, err
    assert not (tmp_path / "run").exists()


@pytest.fixture(scope="module")
def finished_run(scene_dir, tmp_path_factory, run_radfield) -> Path:
    run_dir = tmp_path_factory.mktemp("finished") / "run"
    assert run_radfield("reconstruct", scene_dir, "-o", run_dir, "-q", "--iterations", "30",
                        "--set", "init.num_points=200", "--set", "envelope.target_faces=200") == 0
    return run_dir


@pytest.mark.parametrize("args", [
    ["--iterations", "-5"], ["--iterations", "0"], ["--set", "train.iterations=-5"], ["--max-primitives", "-1"],
    ["--set", "train.lr.means=-1"], ["--set", "train.lr.means=.nan"], ["--set", "train.densify.every=0"],
    ["--set", "render.near=0"], ["--set", "render.hidden=0"], ["--set", "train.sh_degree=4"], ["--seed", "-1"],
    ["--set", "data.background=[0, 2, 0]"], ["--set", "train.checkpoint_every=0"], ["--set", "bake.min_weight=1"],
])
def test_an_out_of_range_number_leaves_a_finished_run_as_it_was(scene_dir, finished_run, cli, args):
    """`reconstruct RUN --iterations -5` on a finished run exited 0 and replaced the trained model by
    an untrained one (issue 44): every number is checked against its range (config.RANGES) when it
    is set, before the run directory is touched."""
    before = snapshot(finished_run)
    code, out, err = cli("reconstruct", scene_dir, "-o", finished_run, "-q", *args)
    assert code == 1 and out == "" and err.startswith("radfield: error: ") and err.count("\n") == 1, err
    assert snapshot(finished_run) == before


# --- init -----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def blobs(scene_dir):
    described, points = data.read_dataset(scene_dir, config()["data"])
    return data.scene_from_json(described, scene_dir), points


def test_init_from_mesh_samples_its_surface(blobs):
    scene, points = blobs
    source, means, rgb = init.initial_centres(scene, points, "auto", 500, np.random.default_rng(0))
    assert source == "mesh" and means.shape == (500, 3) and rgb.shape == (500, 3)
    low, high = points["mesh_vertices"].min(0), points["mesh_vertices"].max(0)
    assert np.all((means >= low - 1e-6) & (means <= high + 1e-6))
    assert len(np.unique(means, axis=0)) == 500 and rgb.std(0).min() > 0.05  # spread, coloured


def test_init_from_points_subsamples_or_repeats(blobs):
    scene, _ = blobs
    rng = np.random.default_rng(0)
    xyz, rgb = rng.normal(size=(50, 3)), rng.random((50, 3))
    points = {"xyz": xyz, "rgb": rgb, "mesh_vertices": np.zeros((0, 3)), "mesh_rgb": np.zeros((0, 3))}
    source, fewer, fewer_rgb = init.initial_centres(scene, points, "auto", 20, rng)
    rows = [int(np.flatnonzero((xyz == p).all(1))[0]) for p in fewer]
    assert source == "points" and len(set(rows)) == 20 and np.array_equal(fewer_rgb, rgb[rows])
    _, more, _ = init.initial_centres(scene, points, "points", 120, rng)
    assert len(np.unique(more, axis=0)) == 120  # repeated points are jittered apart
    assert all((xyz == p).all(1).any() for p in np.unique(xyz, axis=0))
    with pytest.raises(RadfieldError, match="init.source is mesh"):
        init.initial_centres(scene, points, "mesh", 10, rng)


def test_init_random_fills_a_ball_around_the_centre(blobs):
    scene, points = blobs
    source, means, rgb = init.initial_centres(scene, points, "random", 400, np.random.default_rng(0))
    distance = np.linalg.norm(means - scene.normalization.center.numpy(), axis=1)
    radius = init.RANDOM_RADIUS / scene.normalization.scale
    assert source == "random" and rgb is None and distance.max() <= radius and distance.max() > 0.8 * radius


def test_init_stage_budget_and_initial_values(scene_dir, tmp_path):
    run_dir = tmp_path / "run"
    run_until("init", scene_dir, run_dir, config("train.max_primitives=150"))
    assert read_manifest(run_dir / "init")["figures"] == {"primitives": 150, "params": 150 * 99, "source": "mesh",
                                                          "cage_samples": 15, "bound": True}
    model = load_model(run_dir / "init" / init.INIT_MODEL)
    assert model.kind == "neural" and model.sh_degree == 3 and model.omega0 == 10.0 and model.hidden == 8
    assert model.window   # render.window's default
    assert torch.all(model.b2 == torch.tensor(neural.NEURAL_B2))
    assert torch.all(model.log_scales == model.log_scales[:, :1]) and torch.all(model.quats[:, 0] == 1)
    assert torch.all(model.sh[:, 1:] == 0) and not torch.all(model.sh[:, 0] == 0)

    status = run_until("init", scene_dir, run_dir, config("train.max_primitives=150", "train.primitive=gaussian",
                                                          "train.iterations=7"))
    assert status["data"] == "cached" and status["init"] == "ran"
    gaussians = load_model(run_dir / "init" / init.INIT_MODEL)
    assert gaussians.kind == "gaussian" and torch.allclose(torch.sigmoid(gaussians.opacities), torch.tensor(0.1))
    # the same centres; a neural primitive's radius is √7 × the Gaussian's scale (the same spread)
    torch.testing.assert_close(model.means, gaussians.means)
    torch.testing.assert_close(model.log_scales - gaussians.log_scales,
                               torch.full_like(model.log_scales, math.log(math.sqrt(7))))

    status = run_until("init", scene_dir, run_dir, config("train.max_primitives=150", "render.window=false"))
    hard = load_model(run_dir / "init" / init.INIT_MODEL)
    assert status["init"] == "ran" and not hard.window
    torch.testing.assert_close(hard.log_scales - gaussians.log_scales,
                               torch.full_like(hard.log_scales, math.log(math.sqrt(5))))
    run_until("init", scene_dir, run_dir, config("train.max_primitives=150", "init.neural_radius=1.5"))
    torch.testing.assert_close(load_model(run_dir / "init" / init.INIT_MODEL).log_scales - gaussians.log_scales,
                               torch.full_like(hard.log_scales, math.log(1.5)))


@pytest.mark.parametrize("window", [False, True])
def test_neural_radius_factor_matches_the_gaussian_variance(window):
    """Monte Carlo: the density profile of a primitive of radius k = neural_radius_factor has
    per-axis variance 1 (a Gaussian of scale 1's), measured with the renderer's own window."""
    points = torch.rand(400_000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 2 - 1
    r2 = (points ** 2).sum(-1)
    points, r2 = points[r2 <= 1], r2[r2 <= 1]   # uniform in the unit ball
    weight = torch.as_tensor(density_window(SimpleNamespace(window=window), r2), dtype=torch.float64).expand_as(r2)
    variance = (weight[:, None] * points ** 2).sum(0) / weight.sum()   # E[x²] per axis, unit radius
    k = neural.neural_radius_factor(window)
    torch.testing.assert_close(k ** 2 * variance, torch.ones(3, dtype=torch.float64), rtol=0.01, atol=0)


@pytest.mark.parametrize("window", [False, True])
def test_a_new_neural_primitive_has_opacity_one_tenth_through_its_centre(window):
    """With or without the window (whose 1.5 keeps the central chord's optical depth)."""
    means = torch.zeros(400, 3)
    w1, b1, w2, b2 = neural.siren_mlp_init(400, generator=torch.Generator().manual_seed(0))
    prims = neural.NeuralPrimitives(means=means, log_scales=torch.zeros(400, 3),
                                  quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(400, 1), sh=torch.zeros(400, 1, 3),
                                  w1=w1, b1=b1, w2=w2, b2=b2.fill_(neural.NEURAL_B2), window=window)
    dirs = torch.nn.functional.normalize(torch.randn(400, 3, generator=torch.Generator().manual_seed(1)), dim=1)
    depth = neural_line_integral(prims, -5 * dirs, dirs).diagonal()  # ray i through primitive i's centre
    alpha = 1 - torch.exp(-depth.clamp_min(0))
    assert alpha.mean().item() == pytest.approx(0.1, abs=0.01)


# --- eval -----------------------------------------------------------------------------------------


def fake_train(ctx) -> dict:
    """Stands in for training: the initial model is the final one."""
    shutil.copy(ctx.inputs[init.INIT_MODEL], ctx.outputs[MODEL_FILE])
    return {"iterations": 0}


def with_fake_train() -> list[Stage]:
    return [stage if stage.name != "train" else Stage("train", fake_train, ("train",), stage.inputs, (MODEL_FILE,))
            for stage in stages()]


def test_evaluate_metrics(blobs, scene_dir, tmp_path):
    scene, points = blobs
    model_file = tmp_path / "model.safetensors"
    _, means, rgb = init.initial_centres(scene, points, "mesh", 300, np.random.default_rng(0))
    save_model(model_file, init.make_primitives(means, rgb, "gaussian", 1, scene.extent, 0))
    metrics = evaluate(model_file, scene, "test", tmp_path / "renders")
    assert set(metrics) == METRIC_KEYS and metrics["split"] == "test" and metrics["kind"] == "gaussian"
    assert (metrics["num_primitives"], metrics["num_params"]) == (300, 300 * (3 + 3 + 4 + 1 + 12))
    assert metrics["file_size_bytes"] == model_file.stat().st_size and metrics["fps"] > 0
    assert [v["name"] for v in metrics["per_view"]] == ["r_0", "r_1"]
    assert metrics["psnr"] == pytest.approx(np.mean([v["psnr"] for v in metrics["per_view"]]))
    assert 5 < metrics["psnr"] < 40 and 0 < metrics["ssim"] < 1
    assert sorted(p.name for p in (tmp_path / "renders").iterdir()) == ["r_0.png", "r_1.png"]
    with pytest.raises(RadfieldError, match="no 'val' split"):
        evaluate(model_file, scene, "val", tmp_path / "nowhere")


def test_eval_stage_info_json_and_eval_command(scene_dir, tmp_path, cli):
    run_dir = tmp_path / "run"
    status = run_pipeline(with_fake_train(), run_dir, config(), input_path=scene_dir, quiet=True)
    assert status["eval"] == "ran" and status["sfm"] == "not applicable"
    metrics = json.loads((run_dir / "eval" / "metrics.json").read_text())
    assert set(metrics) == METRIC_KEYS and len(list((run_dir / "eval" / "renders").iterdir())) == 2

    code, out, _ = cli("info", run_dir, "--json")
    info = json.loads(out)
    assert code == 0 and set(info) == {"run", "input", "model", "normalization", "pending_checkpoint", "stages",
                                       "imported_from", "edited_from", "edit", "artifacts"}
    assert info["edited_from"] is None and info["edit"] is None and info["imported_from"] is None
    # what each stage wrote, in pipeline order, and the table says it too (it promised "artifacts")
    assert list(info["artifacts"]) == [s for s in info["stages"] if info["stages"][s]["applicable"]]
    assert info["artifacts"]["train"][0] == info["model"] and str(run_dir / "eval" / "report.md") in info["artifacts"]["eval"]
    code, out, _ = cli("info", run_dir)
    assert code == 0 and f"artifacts (in {run_dir}):" in out and "  eval/: metrics.json, renders, report.md" in out
    assert info["pending_checkpoint"] is None
    assert list(info["stages"]) == ["sfm", "data", "triangulate", "envelope", "tetra", "init", "train", "bind", "bake",
                                   "eval"]
    assert info["model"] == str((run_dir / "train" / MODEL_FILE).resolve())
    assert info["stages"]["data"]["images"] == 8 and info["stages"]["sfm"]["applicable"] is False
    assert {"done", "seconds", "psnr", "ssim", "fps"} <= set(info["stages"]["eval"])
    assert info["stages"]["eval"]["psnr"] == pytest.approx(metrics["psnr"])

    code, out, _ = cli("eval", run_dir, "-o", tmp_path / "report", "-q")  # the run's own dataset
    report = json.loads((tmp_path / "report" / "metrics.json").read_text())
    assert code == 0 and "PSNR" in out and report["psnr"] == pytest.approx(metrics["psnr"], abs=1e-4)
    code, _, err = cli("eval", run_dir / "train" / MODEL_FILE, "-o", tmp_path / "r2")
    assert code == 1 and "--dataset" in err and not (tmp_path / "r2").exists()


def test_a_changed_tetra_key_rebinds_and_does_not_retrain(scene_dir, tmp_path):
    # the cage is an input of bind (and init's binding), not of train: a new cage re-binds the
    # trained model in RUN/bind/ and leaves the (expensive) train stage cached
    run_dir, sets = tmp_path / "run", ("train.iterations=2", "train.eval_every=0")
    first = run_pipeline(stages(), run_dir, config(*sets), input_path=scene_dir, until_stage="bind", quiet=True)
    assert first["tetra"] == first["train"] == first["bind"] == "ran"
    model = (run_dir / "train" / MODEL_FILE).read_bytes()
    cage = (run_dir / "tetra" / "cage.npz").read_bytes()
    again = run_pipeline(stages(), run_dir, config(*sets, "tetra.edge_length_fac=0.2"), input_path=scene_dir,
                         until_stage="bind", quiet=True)
    assert again["tetra"] == "ran" and again["train"] == "cached" and again["bind"] == "ran"
    assert (run_dir / "tetra" / "cage.npz").read_bytes() != cage          # the cage did change
    assert (run_dir / "train" / MODEL_FILE).read_bytes() == model
    with np.load(run_dir / "bind" / "model_binding.npz") as binding:
        tets = len(np.load(run_dir / "tetra" / "cage.npz")["tets"])
        assert len(binding["tet"]) == len(load_model(run_dir / "train" / MODEL_FILE)) and binding["tet"].max() < tets
    assert not (run_dir / "train" / "model_binding.npz").exists()


def test_demo_scene_command(tmp_path, cli):
    code, out, _ = cli("demo-scene", "checker", "-o", tmp_path / "c", "--train-views", "2", "--test-views", "1",
                       "--size", "8")
    assert code == 0 and (tmp_path / "c" / "transforms_train.json").is_file() and "checker" in out
    code, _, err = cli("demo-scene", "nope", "-o", tmp_path / "d")
    assert code == 1 and "unknown demo scene" in err


# --- reconstruct end to end -------------------------------------------------------------------------


def test_reconstruct_caches_and_reruns_only_what_changed(scene_dir, tmp_path, cli):
    run_dir = tmp_path / "run"
    args = ["reconstruct", scene_dir, "-o", run_dir, "-q", "--set", "init.num_points=300"]
    code, out, err = cli(*args, "--set", "train.iterations=40")
    assert code == 0, err
    assert "held-out PSNR" in out
    info = json.loads(cli("info", run_dir, "--json")[1])
    assert {"primitives", "params", "iterations", "train_psnr"} <= set(info["stages"]["train"])
    initial = evaluate(run_dir / "init" / init.INIT_MODEL, data.load_scene(run_dir / "data" / data.SCENE), "test",
                       tmp_path / "initial")
    assert info["stages"]["eval"]["psnr"] > initial["psnr"] + 1.0

    code, out, _ = cli(*args, "--set", "train.iterations=40")
    assert code == 0 and out.splitlines()[0] == "stages: " + ", ".join(f"{name} cached" for name in info["stages"])

    code, out, err = cli(*args, "--set", "train.iterations=41")
    outcomes = dict(part.split(" ", 1) for part in out.splitlines()[0].removeprefix("stages: ").split(", "))
    assert code == 0 and [name for name, outcome in outcomes.items() if outcome == "ran"] == ["train", "bind", "bake", "eval"]
    info = json.loads(cli("info", run_dir, "--json")[1])
    assert math.isfinite(info["stages"]["eval"]["psnr"])
    # one more step continues the finished run; its log has every step once
    assert info["stages"]["train"]["continued_from"] == 40 and info["stages"]["train"]["iterations"] == 41
    log = [json.loads(line) for line in (run_dir / "train" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == list(range(1, 42)) and (run_dir / "train" / "curves.png").is_file()

    # render RUN: the run's own dataset, test split, background and near plane (= the eval renders)
    code, out, err = cli("render", run_dir, "-o", tmp_path / "frames", "-q")
    assert code == 0, err
    eval_renders = sorted(p.name for p in (run_dir / "eval" / "renders").iterdir())
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == eval_renders
    for name in eval_renders:
        assert np.array_equal(read_image(tmp_path / "frames" / name), read_image(run_dir / "eval" / "renders" / name))
    # an explicit option wins
    code, _, err = cli("render", run_dir, "-o", tmp_path / "black", "-q", "--background", "0,0,0", "--split", "train")
    assert code == 0, err
    assert len(list((tmp_path / "black").iterdir())) == 6
    assert read_image(tmp_path / "black" / "r_0.png").min() < 0.05  # the background shows black

    # an interrupted training shows its pending checkpoint
    assert info["pending_checkpoint"] is None
    state = load_checkpoint(run_dir / "train" / "final_state.safetensors")
    save_checkpoint(run_dir / "train.work" / "checkpoint.safetensors", dataclasses.replace(state, step=7))
    info = json.loads(cli("info", run_dir, "--json")[1])
    pending = info["pending_checkpoint"]
    assert (pending["stage"], pending["step"], pending["iterations"]) == ("train", 7, 41)
    assert "pending checkpoint: train interrupted at step 7 of 41" in cli("info", run_dir)[1]
