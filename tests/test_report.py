"""`radfield eval` report files, `eval --compare` and `bench-quality`, on a tiny generated scene
(32×32 views: just above LPIPS' smallest input)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from radfield.evaluation import lpips as lpips_metric
from radfield.model_file import save_model
from radfield.evaluation.report import BAR_STRIP, BAR_WIDTH, GAP, LABEL_HEIGHT, error_map
from radfield.datasets.images import read_image
from radfield.demo.static import generate_scene
from radfield.datasets import scene as data
from radfield.stages import init
from radfield.pipeline.config import load_config

CI = os.environ.get("CI", "").lower() == "true"
SIZE = 32


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    return generate_scene("blobs", tmp_path_factory.mktemp("data") / "blobs", n_train=4, n_test=2, size=SIZE)


@pytest.fixture(scope="module")
def models(scene_dir, tmp_path_factory) -> dict[str, Path]:
    """A neural and a Gaussian model initialised on the scene's mesh (untrained, but not blank)."""
    folder = tmp_path_factory.mktemp("models")
    scene_json, points = data.read_dataset(scene_dir, load_config()["data"])
    scene = data.scene_from_json(scene_json, scene_dir)
    out = {}
    for kind in ("neural", "gaussian"):
        _, means, rgb = init.initial_centres(scene, points, "mesh", 150, np.random.default_rng(0))
        out[kind] = folder / f"{kind}.safetensors"
        save_model(out[kind], init.make_primitives(means, rgb, kind, 0, scene.extent, 0))
    return out


def _lpips_required() -> bool:
    try:
        lpips_metric.load_network()
        return True
    except lpips_metric.Unavailable as e:
        if CI:
            pytest.fail(f"{e} (CI=true)")
        return False


def test_eval_writes_report_grids_and_lpips(scene_dir, models, tmp_path, cli):
    out = tmp_path / "report"
    code, stdout, err = cli("eval", models["neural"], "-d", scene_dir, "-o", out, "-q")
    assert code == 0, err
    metrics = json.loads((out / "metrics.json").read_text())
    text = (out / "report.md").read_text()
    for v in metrics["per_view"]:
        assert f"| {v['name']} | {v['psnr']:.2f} | {v['ssim']:.4f} |" in text
        grid = read_image(out / "grids" / f"{v['name']}.png")
        # captioned panels (truth | render | |error|) and the error map's colour bar
        assert grid.shape[:2] == (LABEL_HEIGHT + SIZE, 3 * SIZE + BAR_WIDTH + 3 * GAP)
        render = read_image(out / "renders" / f"{v['name']}.png")[..., :3]
        np.testing.assert_allclose(grid[LABEL_HEIGHT:, SIZE + GAP : 2 * SIZE + GAP, :3], render, atol=1 / 255)
        assert grid[:LABEL_HEIGHT, :SIZE].min() < 0.5                      # a caption is written
        bar = grid[LABEL_HEIGHT:, 3 * SIZE + 3 * GAP:3 * SIZE + 3 * GAP + BAR_STRIP, :3]
        np.testing.assert_allclose(bar[-1], np.broadcast_to(error_map(np.zeros((1, 1, 3)), np.zeros((1, 1, 3)))[0], bar[-1].shape), atol=0.02)   # 0: black
        assert bar[0].mean() > 0.8 and bar[0].mean() > bar[SIZE // 2].mean() > bar[-1].mean()   # ERROR_SCALE on top
    assert f"**{metrics['psnr']:.2f}**" in text and f"| primitives | {metrics['num_primitives']} |" in text
    assert f"| parameters | {metrics['num_params']} |" in text and f"{metrics['fps']:.2f}" in text
    if _lpips_required():
        assert metrics["lpips"] is not None and f"**{metrics['lpips']:.4f}**" in text
        assert metrics["lpips"] == pytest.approx(np.mean([v["lpips"] for v in metrics["per_view"]]))
        assert 0 < metrics["lpips"] < 1 and "LPIPS" in stdout
    assert not list(tmp_path.glob(".report.tmp-*"))


def test_error_map_scale():
    a = np.zeros((2, 2, 3), np.float32)
    b = a.copy()
    b[0, 0] = 1.0
    heat = error_map(b, a)
    assert heat[1, 1].sum() < 0.05 and heat[0, 0].sum() > 2.0   # inferno: black at 0, bright at the top


def test_compare_table_and_side_by_side(scene_dir, models, tmp_path, cli):
    out = tmp_path / "cmp"
    code, stdout, err = cli("eval", "--compare", models["neural"], models["gaussian"], "-d", scene_dir, "-o", out, "-q")
    assert code == 0, err
    rows = json.loads((out / "comparison.json").read_text())
    assert [r["label"] for r in rows] == ["neural", "gaussian"]
    text = (out / "report.md").read_text()
    for row in rows:
        m = row["metrics"]
        assert m == json.loads((out / row["label"] / "metrics.json").read_text())
        assert f"| {row['label']} | {m['kind']} | {m['psnr']:.2f} | {m['ssim']:.4f} |" in text
    assert rows[0]["metrics"]["kind"] == "neural" and rows[1]["metrics"]["kind"] == "gaussian"
    grid = read_image(out / "grids" / "r_0.png")
    assert grid.shape[:2] == (SIZE + LABEL_HEIGHT, 3 * SIZE + 2 * GAP)
    code, _, err = cli("eval", models["neural"], models["gaussian"], "-d", scene_dir, "-o", tmp_path / "x")
    assert code == 1 and "--compare" in err and not (tmp_path / "x").exists()


@pytest.mark.slow
def test_bench_quality_tiny(scene_dir, tmp_path, cli):
    out = tmp_path / "bench"
    code, stdout, err = cli("bench-quality", scene_dir, "-o", out, "--budgets", "40,none", "--kinds", "neural",
                            "--iterations", "3", "--set", "init.num_points=60", "--set", "envelope.target_faces=200", "-q")
    assert code == 0, err + stdout
    rows = json.loads((out / "bench.json").read_text())
    assert [(r["kind"], r["budget"]) for r in rows] == [("neural", 40), ("neural", None)]
    assert all("error" not in r for r in rows), rows
    for r in rows:
        metrics = json.loads((Path(r["run"]) / "eval" / "metrics.json").read_text())
        assert r["psnr"] == metrics["psnr"] and r["params"] == metrics["num_params"]
        if r["budget"] is not None:
            assert r["primitives"] <= r["budget"]
    assert (out / "psnr_vs_params.png").stat().st_size > 1000
    table = (out / "bench.md").read_text()
    assert table.count("\n| ") == 4 and f"{rows[0]['psnr']:.2f}" in table  # header, rule, two rows


def test_the_time_plot_legend_hides_no_point():
    """In the corner the legend hid the last moment's point (issue 44): it is below the axes."""
    from radfield.evaluation.report import time_figure

    per_time = [{"time": k / 23, "psnr": 40.0 - 3.0 * (k == 23), "views": 4} for k in range(24)]
    figure = time_figure(per_time)
    figure.canvas.draw()
    axes = figure.axes[0]
    legend = (figure.legends or [axes.get_legend()])[0].get_window_extent()
    points = axes.transData.transform([(t["time"], t["psnr"]) for t in per_time])
    assert not any(legend.contains(x, y) for x, y in points)
    assert not legend.overlaps(axes.get_window_extent())
