"""Relighting through the pipeline (issue 30): `reconstruct` picks the relightable kind on a dataset
whose views carry a light (data.light=ignore trains the static kind: the light-blind baseline),
the run records it, `eval` scores held-out (camera, light) frames per light, and views that carry a
time and a light have no kind. (A run under fixed lighting, a relightable kind on views without
lights or with data.light=ignore, a bad light setting: test_conditions.py.)"""

import json
from pathlib import Path

import numpy as np
import pytest

from radfield.demo.olat import generate_olat
from radfield.model_file import load_model
from radfield.errors import RadfieldError
from radfield.pipeline.config import load_defaults
from radfield.stages.init import primitive_kind

STEPS = "300"   # no densification before step 500: every run keeps its 2000 initial primitives


@pytest.fixture(scope="module")
def olat(tmp_path_factory) -> Path:
    """The olat scene at 20 px: 6 train cameras × 4 lights, 2 test cameras × 4 lights never seen; with
    its mesh.ply, so the primitives start on the surface (from the random ball, 300 steps are too few
    for either model to find the objects: both ~17.9 dB)."""
    return generate_olat(tmp_path_factory.mktemp("olat") / "olat", n_train=6, n_test=2, lights=4, size=20)


@pytest.fixture(scope="module")
def runs(olat, tmp_path_factory, run_radfield) -> dict[str, Path]:
    """A relit run (the default: neural -> neural-relight) and the light-blind one of the same frames."""
    root = tmp_path_factory.mktemp("runs")
    for name, extra in (("relit", []), ("blind", ["--set", "data.light=ignore"])):
        assert run_radfield("reconstruct", olat, "-o", root / name, "--no-cage", "--iterations", STEPS, "-q", *extra) == 0
    return {"relit": root / "relit", "blind": root / "blind"}


def metrics(run: Path) -> dict:
    return json.loads((run / "eval" / "metrics.json").read_text())


# --- kind selection and the light-blind baseline ---------------------------------------------------


def test_a_relighting_dataset_trains_the_relightable_kind_and_beats_the_light_blind_model(cli, runs):
    relit, blind = metrics(runs["relit"]), metrics(runs["blind"])
    assert relit["kind"] == "neural-relight" and blind["kind"] == "neural"
    assert load_model(runs["relit"] / "train" / "model.safetensors").kind == "neural-relight"
    # the same held-out frames: 2 cameras × 4 lights, none of them a training light
    assert relit["views"] == blind["views"] == 8
    # measured at 300 steps, 20 px: relit 21.2 dB, light-blind 17.5 dB
    assert relit["psnr"] > blind["psnr"] + 2.5, (relit["psnr"], blind["psnr"])
    # eq. 14 as written: the relightable kinds train SH degree 0 (the constant c_dc), whatever train.sh_degree
    assert load_model(runs["relit"] / "train" / "model.safetensors").sh_degree == 0
    assert load_model(runs["blind"] / "train" / "model.safetensors").sh_degree == 3
    # bake keeps the kind (its coverage and PSNR are taken under every view's own light)
    assert load_model(runs["relit"] / "bake" / "baked.safetensors").kind == "neural-relight"


def test_the_run_records_the_lights_and_the_kind(cli, runs):
    code, out, _ = cli("info", runs["relit"], "--json")
    stages = json.loads(out)["stages"]
    assert stages["init"]["kind"] == "neural-relight" and stages["data"]["lights"] == 32
    assert "relightable scene: 32 lights, primitive kind neural-relight" in cli("info", runs["relit"])[1]
    code, out, _ = cli("info", runs["blind"], "--json")
    blind = json.loads(out)["stages"]
    assert "kind" not in blind["init"] and "lights" not in blind["data"]
    assert "relightable scene" not in cli("info", runs["blind"])[1]


def test_reconstruct_says_which_kind_the_lights_chose(cli, olat, tmp_path):
    code, out, err = cli("reconstruct", olat, "-o", tmp_path / "run", "--no-cage", "--iterations", "5", "-q",
                         "--primitive", "gaussian")
    assert code == 0, err
    assert "relightable scene: 32 lights, gaussian-relight primitives" in out
    assert metrics(tmp_path / "run")["kind"] == "gaussian-relight"


# --- eval: per-light figures ------------------------------------------------------------------------


def test_eval_reports_every_test_light_consistently_with_the_overall_mean(cli, olat, runs, tmp_path):
    test_frames = json.loads((olat / "transforms_test.json").read_text())["frames"]
    # the light-blind run's views carry no light (data.light=ignore): its model file measured on the
    # dataset gets the per-light figures of the same lights
    assert "per_light" not in metrics(runs["blind"])
    code, _, err = cli("eval", runs["blind"] / "train" / "model.safetensors", "--dataset", olat, "-o", tmp_path / "blind", "-q")
    assert code == 0, err
    blind = json.loads((tmp_path / "blind" / "metrics.json").read_text())
    assert blind["psnr"] == pytest.approx(metrics(runs["blind"])["psnr"], abs=1e-6)
    for m in (metrics(runs["relit"]), blind):
        per_light = m["per_light"]
        # each test frame has its own light: its position and intensity, as the dataset gives them
        assert (np.array([light["position"] for light in per_light])
                == pytest.approx(np.array([f["light_position"] for f in test_frames])))
        assert [light["intensity"] for light in per_light] == pytest.approx([f["light_intensity"] for f in test_frames])
        assert all(light["views"] == 1 for light in per_light)
        for key in ("psnr", "ssim"):
            mean = sum(light[key] * light["views"] for light in per_light) / sum(light["views"] for light in per_light)
            assert mean == pytest.approx(m[key], rel=1e-12)
            assert [light[key] for light in per_light] == pytest.approx([v[key] for v in m["per_view"]], rel=1e-12)
        assert all(light["lpips"] is None for light in per_light)   # 20 px: below LPIPS' 31 px
    report = (runs["relit"] / "eval" / "report.md").read_text()
    assert "## Per light" in report and report.count("| at ") == 8
    # `radfield eval` on the run writes the same per-light figures
    code, out, err = cli("eval", runs["relit"], "-o", tmp_path / "again", "-q")
    assert code == 0, err
    per_light = metrics(runs["relit"])["per_light"]
    assert f"8 lights: PSNR from {min(x['psnr'] for x in per_light):.2f} dB" in out
    again = json.loads((tmp_path / "again" / "metrics.json").read_text())
    assert [x["psnr"] for x in again["per_light"]] == pytest.approx([x["psnr"] for x in per_light], abs=1e-9)


# --- mistakes: one line, nothing written ------------------------------------------------------------


def test_views_that_carry_a_time_and_a_light_have_no_kind_for_both():
    config = load_defaults()
    for ignored, kind in (("light", "neural-dynamic"), ("time", "neural-relight")):
        assert primitive_kind(config, [c for c in ("time", "light") if c != ignored]) == kind
    with pytest.raises(RadfieldError, match="no variant conditioned on light and time.*data.light=ignore or "
                                            "data.time=ignore"):
        primitive_kind(config, ("time", "light"))


# --- bench-quality names the kind that trained ------------------------------------------------------


def test_bench_quality_shows_the_relightable_kind_that_trained(cli, olat, tmp_path):
    out = tmp_path / "bench"
    code, stdout, err = cli("bench-quality", olat, "-o", out, "--budgets", "40", "--kinds", "neural", "--iterations", "3",
                            "--set", "envelope.source=none", "--jobs", "1", "-q")
    assert code == 0, err + stdout
    rows = json.loads((out / "bench.json").read_text())
    assert [(r["kind"], r["budget"]) for r in rows] == [("neural-relight", 40)], rows
    assert Path(rows[0]["run"]).name == "neural-40"   # the run folder keeps the --kinds name
    assert "| 40 | neural-relight |" in (out / "bench.md").read_text()
