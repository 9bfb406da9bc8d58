"""Dynamic scenes through the pipeline (issue 29): `reconstruct` picks the time-conditioned kind on
a dataset whose views carry a time (data.time=ignore trains the static kind: the baseline), the
envelope holds the object at every moment, `eval` reports per-time figures and a PSNR-over-time
plot, and bake keeps the kind. (A static run, a dynamic kind on views without time or with
data.time=ignore, bad time settings: test_conditions.py.)"""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from radfield.core.geometry.envelope import read_envelope, visual_hull
from radfield.datasets.scene import read_dataset, scene_from_json
from radfield.demo.timelapse import generate_dynamic
from radfield.model_file import load_model
from radfield.pipeline.config import load_defaults

TIMES = [0.0, 0.5, 1.0]
STEPS = "200"   # no densification before step 500: every run keeps its 2000 initial primitives


@pytest.fixture(scope="module")
def smoke(tmp_path_factory) -> Path:
    """The smoke volume at 16 px: 4 train + 2 test cameras, each at 3 times."""
    return generate_dynamic("smoke", tmp_path_factory.mktemp("smoke") / "smoke", n_train=4, n_test=2, times=3, size=16)


@pytest.fixture(scope="module")
def moving(tmp_path_factory) -> Path:
    """The moving opaque shapes at 24 px: 12 train cameras a moment (enough for per-moment hulls)."""
    return generate_dynamic("moving", tmp_path_factory.mktemp("moving") / "moving", n_train=12, n_test=1, times=3, size=24)


def metrics(run: Path) -> dict:
    return json.loads((run / "eval" / "metrics.json").read_text())


def reconstruct(cli, dataset: Path, run: Path, *args, steps: str = STEPS) -> dict:
    code, out, err = cli("reconstruct", dataset, "-o", run, "--no-cage", "--iterations", steps, "-q", *args)
    assert code == 0, err
    dynamic = "data.time=ignore" not in args and dataset.name in ("smoke", "moving")
    assert ("dynamic scene: 3 moments, " in out) == dynamic, out
    return metrics(run)


# --- kind selection and the time-ignored baseline -------------------------------------------------


@pytest.mark.parametrize("primitive", ["neural", "gaussian"])
def test_a_dynamic_dataset_trains_the_time_conditioned_kind_and_beats_the_static_baseline(cli, smoke, tmp_path, primitive):
    dynamic = reconstruct(cli, smoke, tmp_path / "dynamic", "--primitive", primitive)
    static = reconstruct(cli, smoke, tmp_path / "static", "--primitive", primitive, "--set", "data.time=ignore")
    assert dynamic["kind"] == f"{primitive}-dynamic" and static["kind"] == primitive
    assert load_model(tmp_path / "dynamic" / "train" / "model.safetensors").kind == f"{primitive}-dynamic"
    # the run records it: `radfield info` shows the kind and the dataset's moments
    code, out, _ = cli("info", tmp_path / "dynamic", "--json")
    stages = json.loads(out)["stages"]
    assert stages["init"]["kind"] == f"{primitive}-dynamic" and stages["data"]["times"] == 3
    assert f"dynamic scene: 3 moments, primitive kind {primitive}-dynamic" in cli("info", tmp_path / "dynamic")[1]
    code, out, _ = cli("info", tmp_path / "static", "--json")
    static_stages = json.loads(out)["stages"]
    assert "kind" not in static_stages["init"] and "times" not in static_stages["data"]
    # measured: neural +2.5 dB, gaussian +4.5 dB at 200 steps; the same test views, time-ignored
    assert dynamic["views"] == static["views"] == 6
    assert dynamic["psnr"] > static["psnr"] + 1.5, (dynamic["psnr"], static["psnr"])
    # bake keeps the kind (its coverage and PSNR are taken at every view's own time)
    assert load_model(tmp_path / "dynamic" / "bake" / "baked.safetensors").kind == f"{primitive}-dynamic"


def test_time_frequency_reaches_the_model_file(cli, smoke, tmp_path):
    cli("reconstruct", smoke, "-o", tmp_path / "run", "--no-cage", "--until", "init", "-q",
        "--set", "render.time_frequency=6.283185")
    assert load_model(tmp_path / "run" / "init" / "init.safetensors").time_frequency == pytest.approx(6.283185)
    # what moves does not triangulate: the start is random, each primitive a few pixels
    triangulate = json.loads((tmp_path / "run" / "triangulate" / "manifest.json").read_text())
    assert triangulate["applicable"] is False and triangulate["reason"].startswith("a dynamic scene")
    assert json.loads((tmp_path / "run" / "init" / "manifest.json").read_text())["figures"]["source"] == "random"


# --- eval: per-time figures and the plot ---------------------------------------------------------


def test_eval_reports_every_moment_consistently_with_the_overall_mean(cli, smoke, tmp_path):
    m = reconstruct(cli, smoke, tmp_path / "run")
    assert [v["time"] for v in m["per_view"]] == [t for _ in range(2) for t in TIMES]  # r_000 t0..t2, r_001 ...
    per_time = m["per_time"]
    assert [t["time"] for t in per_time] == TIMES and all(t["views"] == 2 for t in per_time)
    for key in ("psnr", "ssim"):
        mean = sum(t[key] * t["views"] for t in per_time) / sum(t["views"] for t in per_time)
        assert mean == pytest.approx(m[key], rel=1e-12)
        for t in per_time:   # each moment's figure is the mean of its own views
            own = [v[key] for v in m["per_view"] if v["time"] == t["time"]]
            assert t[key] == pytest.approx(sum(own) / len(own), rel=1e-12)
    assert all(t["lpips"] is None for t in per_time)   # 16 px: below LPIPS' 31 px, as the overall figure
    report = (tmp_path / "run" / "eval" / "report.md").read_text()
    assert "## Over time" in report and "](figures/psnr_over_time.png)" in report
    plot = cv2.imread(str(tmp_path / "run" / "eval" / "figures" / "psnr_over_time.png"))
    assert plot is not None and plot.shape[0] > 100 and plot.std() > 0
    # `radfield eval` on the run writes the same per-time figures
    code, out, err = cli("eval", tmp_path / "run", "-o", tmp_path / "again", "-q")
    assert code == 0, err
    worst = min(per_time, key=lambda t: t["psnr"])
    assert f"3 moments: PSNR from {worst['psnr']:.2f} dB (time {worst['time']:.4g})" in out
    again = json.loads((tmp_path / "again" / "metrics.json").read_text())
    assert [t["psnr"] for t in again["per_time"]] == pytest.approx([t["psnr"] for t in per_time], abs=1e-9)
    assert (tmp_path / "again" / "figures" / "psnr_over_time.png").is_file()


# --- the envelope of a moving object -------------------------------------------------------------


def silhouette(vertices: np.ndarray, faces: np.ndarray, camera) -> np.ndarray:
    """(H, W) bool: the pixels whose centres the envelope's projection covers (filled triangles)."""
    w2c = camera.w2c.numpy()
    p = vertices @ w2c[:3, :3].T + w2c[:3, 3]
    assert (p[:, 2] > 0).all()  # the envelope lies in front of every camera
    uv = np.stack([camera.fx * p[:, 0] / p[:, 2] + camera.cx, camera.fy * p[:, 1] / p[:, 2] + camera.cy], -1)
    image = np.zeros((camera.height, camera.width), np.uint8)
    for triangle in faces:   # pixel k's centre is at k + 0.5; 4 fractional bits
        cv2.fillPoly(image, [np.round((uv[triangle] - 0.5) * 16).astype(np.int32)], 1, shift=4)
    return image > 0


def uncovered(vertices, faces, cameras, masks) -> list[int]:
    """Per view: its foreground pixels outside the envelope's projection."""
    return [int(((mask > 0.5) & ~silhouette(vertices, faces, camera)).sum()) for camera, mask in zip(cameras, masks)]


def test_the_envelope_of_a_moving_object_holds_it_at_every_moment(cli, moving, tmp_path):
    code, _, err = cli("reconstruct", moving, "-o", tmp_path / "run", "--until", "envelope", "-q")
    assert code == 0, err
    code, out, _ = cli("info", tmp_path / "run", "--json")
    figures = json.loads(out)["stages"]["envelope"]
    assert figures["source"] == "hull" and figures["moments"] == 3 and figures["fallback"] is None
    train = scene_from_json(read_dataset(moving, load_defaults()["data"])[0], moving).dataset("train")
    cameras, masks = train.cameras, list(train.load_images()[1].numpy())
    assert sorted({c.conditions["time"] for c in cameras}) == TIMES
    union = uncovered(*read_envelope(tmp_path / "run" / "envelope" / "envelope.ply"), cameras, masks)
    assert union == [0] * len(cameras)
    # the plain visual hull, carved by the views of every moment at once, cuts moving parts away
    v, f, _ = visual_hull(cameras, masks, load_defaults()["envelope"])
    plain = uncovered(v, f, cameras, masks)
    assert sum(plain) > 20 and sum(n > 0 for n in plain) > len(cameras) // 2, plain


def test_a_monocular_dynamic_capture_gets_the_box_about_the_cameras_focus(cli, moving, tmp_path):
    # D-NeRF's monocular layout: one view a moment (here: training camera k at time k only, k < 3)
    mono = tmp_path / "mono"
    mono.mkdir()
    for name in ("train", "test"):
        (mono / name).symlink_to(moving / name)
        meta = json.loads((moving / f"transforms_{name}.json").read_text())
        if name == "train":   # file_path ./train/r_CCC_tTTT
            meta["frames"] = [f for f in meta["frames"] if int(f["file_path"].split("_")[-2]) == TIMES.index(f["time"])]
        (mono / f"transforms_{name}.json").write_text(json.dumps(meta))
    code, _, err = cli("reconstruct", mono, "-o", tmp_path / "run", "--until", "envelope", "-q")
    assert code == 0, err
    assert "fell back to the box" in err and "too few for per-moment hulls" in err
    code, out, _ = cli("info", tmp_path / "run", "--json")
    figures = json.loads(out)["stages"]["envelope"]
    assert figures["method"] == "box" and figures["moments"] == 3
    # the box about the cameras' focus holds the object at every moment (each view's silhouette)
    train = scene_from_json(read_dataset(mono, load_defaults()["data"])[0], mono).dataset("train")
    assert sorted(c.conditions["time"] for c in train.cameras) == TIMES
    v, f = read_envelope(tmp_path / "run" / "envelope" / "envelope.ply")
    assert len(v) == 8
    assert uncovered(v, f, train.cameras, list(train.load_images()[1].numpy())) == [0, 0, 0]


# --- bake and edit on a dynamic run ----------------------------------------------------------------


@pytest.mark.slow   # the envelope and fTetWild's cage: about 10 s
def test_a_caged_dynamic_run_edits_bakes_and_evaluates_at_every_moment(cli, smoke, tmp_path):
    code, _, err = cli("reconstruct", smoke, "-o", tmp_path / "run", "--iterations", "50", "-q")
    assert code == 0, err
    code, out, _ = cli("info", tmp_path / "run", "--json")
    stages = json.loads(out)["stages"]
    assert stages["envelope"]["moments"] == 3 and stages["init"]["bound"] and stages["init"]["kind"] == "neural-dynamic"
    spec = tmp_path / "twist.yaml"
    spec.write_text("operations:\n  - twist: {axis: z, degrees_per_unit: 20}\n")
    code, _, err = cli("edit", tmp_path / "run", "--spec", spec, "-o", tmp_path / "edited", "-q")
    assert code == 0, err
    edited = load_model(tmp_path / "edited" / "edit" / "model.safetensors")
    source = load_model(tmp_path / "run" / "train" / "model.safetensors")
    # the cage's map moves the geometry; the temporal tensors ride along (an edit commutes with time)
    assert edited.kind == "neural-dynamic" and len(edited) >= len(source)
    assert not np.allclose(edited.means[: len(source)].numpy(), source.means.numpy())
    code, out, err = cli("eval", tmp_path / "edited", "-o", tmp_path / "report", "-q")
    assert code == 0 and "3 moments" in out, err
    code, out, err = cli("bake", tmp_path / "edited", "-o", tmp_path / "baked.safetensors", "-q")
    assert code == 0, err
    assert load_model(tmp_path / "baked.safetensors").kind == "neural-dynamic"
