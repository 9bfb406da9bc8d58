"""`radfield bench-quality`'s protocol without running it (the tiny end-to-end run is in
test_report.py): the reconstruct command of each (kind, budget), the scaled densification
schedule, budgets parsing and the table."""

from __future__ import annotations

from pathlib import Path

import pytest

from radfield.bench.quality import default_iterations, parse_budgets, reconstruct_args, schedule, table
from radfield.errors import RadfieldError
from radfield.pipeline.config import load_config, load_defaults


def sets_of(args: list[str]) -> list[str]:
    return [args[k + 1] for k, a in enumerate(args) if a == "--set"]


def test_at_the_default_iterations_an_unbudgeted_run_is_a_default_run():
    n = default_iterations()
    assert n == load_defaults()["train"]["iterations"]
    args = reconstruct_args(Path("D"), Path("R"), "gaussian", None, n, ["data.downscale=2"])
    assert "--max-primitives" not in args and args[args.index("--primitive") + 1] == "gaussian"
    config = load_config(sets=sets_of(args))
    defaults = load_defaults()
    assert config["train"]["densify"] == defaults["train"]["densify"]  # the schedule sets change nothing
    assert config["data"]["downscale"] == 2  # the user's --set comes last


def test_shorter_runs_scale_the_schedule_and_budgets_are_passed():
    d = load_defaults()["train"]
    half = d["iterations"] // 2
    s = schedule(half)
    assert s["train.densify.start"] == round(d["densify"]["start"] / 2)
    assert s["train.densify.stop"] == round(d["densify"]["stop"] / 2)
    assert s["train.densify.gaussian.opacity_reset_every"] == round(d["densify"]["gaussian"]["opacity_reset_every"] / 2)
    assert s["train.densify.start"] < s["train.densify.stop"] <= half
    args = reconstruct_args(Path("D"), Path("R"), "neural", 500, half, [])
    assert args[args.index("--max-primitives") + 1] == "500" and args[args.index("--iterations") + 1] == str(half)
    assert schedule(1)["train.densify.gaussian.opacity_reset_every"] == 1


def test_parse_budgets():
    assert parse_budgets("500, 2000,8000,none") == [500, 2000, 8000, None]
    for bad in ("0", "abc", "500,500", ""):
        with pytest.raises(RadfieldError):
            parse_budgets(bad)


def test_table_rows_have_every_column():
    ok = {"kind": "neural", "budget": 500, "run": "r", "psnr": 30.123, "ssim": 0.9, "lpips": None, "primitives": 500,
          "params": 5000, "size_bytes": 20000, "fps": 10.0, "train_seconds": 42.0, "train_psnr": 31.0,
          "stage_seconds": {"train": 42.0, "bake": 3.0}, "pipeline_seconds": 45.0}
    failed = {"kind": "gaussian", "budget": None, "run": "r2", "error": "boom"}
    lines = table([ok, failed], dataset=Path("D"), iterations=3000).splitlines()
    rows = [line for line in lines if line.startswith("|")]
    assert len({row.count("|") for row in rows}) == 1  # header, rule and both rows: the same columns
    assert "30.12" in rows[2] and "42 s" in rows[2] and "45 s" in rows[2] and "boom" in rows[3]
