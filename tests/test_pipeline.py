"""The stage pipeline machinery and the configuration, with toy stages (no torch, no data)."""

from __future__ import annotations

import collections
import fcntl
import json
from pathlib import Path
from typing import Any

import pytest
import yaml

from radfield.errors import RadfieldError
from radfield.pipeline import schema
from radfield.pipeline.config import load_config, load_defaults, parse_set, save_resolved, section
from radfield.pipeline.info import format_info, run_info
from radfield.pipeline.runner import INPUT, Context, NotApplicable, Stage, read_manifest, run_pipeline
from radfield.run import MODEL_FILE, Run

ORDER = ["data", "sfm", "init", "train", "eval"]


class Toy:
    """A five-stage toy pipeline that counts calls; `train` checkpoints one file per step."""

    def __init__(self) -> None:
        self.calls: collections.Counter[str] = collections.Counter()
        self.fail_train_at: int | None = None  # step at which train raises (a simulated kill)
        self.train_started_at: list[int] = []

    def stages(self) -> list[Stage]:
        return [
            Stage("data", self.data, ("data",), (INPUT,), ("scene.txt",)),
            Stage("sfm", self.sfm, ("sfm",), ("scene.txt",), ("points.txt",)),
            Stage("init", self.init, ("init", "seed"), ("scene.txt", "points.txt"), ("prims",)),
            Stage("train", self.train, ("train", "render"), ("prims",), (MODEL_FILE,)),
            Stage("eval", self.eval, ("eval",), (MODEL_FILE,), ("metrics.json",)),
        ]

    def data(self, ctx: Context) -> dict[str, Any]:
        self.calls["data"] += 1
        text = (ctx.inputs[INPUT] / "transforms.json").read_text() * ctx.config["data"]["repeat"]
        ctx.outputs["scene.txt"].write_text(text)
        return {"images": len(text)}

    def sfm(self, ctx: Context) -> None:
        self.calls["sfm"] += 1
        if ctx.config["sfm"]["posed"]:
            raise NotApplicable("the dataset has poses")
        ctx.outputs["points.txt"].write_text("points")

    def init(self, ctx: Context) -> dict[str, Any]:
        self.calls["init"] += 1
        assert ctx.inputs["points.txt"] is None  # sfm was not applicable
        prims = ctx.outputs["prims"]
        prims.mkdir()
        for i in range(ctx.config["init"]["count"]):
            (prims / f"{i}.txt").write_text(f"{ctx.inputs['scene.txt'].read_text()} {ctx.seed} {i}")
        return {"primitives": ctx.config["init"]["count"]}

    def train(self, ctx: Context) -> dict[str, Any]:
        self.calls["train"] += 1
        steps = ctx.config["train"]["iterations"]
        done = sorted(int(p.stem) for p in ctx.work.glob("*.ckpt"))
        start = done[-1] + 1 if done else 0
        self.train_started_at.append(start)
        for step in range(start, steps):
            if step == self.fail_train_at:
                raise KeyboardInterrupt  # what a user's Ctrl-C looks like to the stage
            (ctx.work / f"{step}.ckpt").write_text(str(step))
        files = sorted(p.name for p in ctx.inputs["prims"].iterdir())
        ctx.outputs[MODEL_FILE].write_text(f"{files} {steps} {ctx.config['render']['near']}")
        return {"iterations": steps, "train_psnr": 30.5}

    def eval(self, ctx: Context) -> dict[str, Any]:
        self.calls["eval"] += 1
        ctx.outputs["metrics.json"].write_text(json.dumps({"model": ctx.inputs[MODEL_FILE].read_text()}))
        return {"psnr": 29.0}


@pytest.fixture
def toy() -> Toy:
    return Toy()


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    path = tmp_path / "dataset"
    path.mkdir()
    (path / "transforms.json").write_text("scene")
    return path


def base_config() -> dict[str, Any]:
    return {
        "stages": list(ORDER),
        "seed": 0,
        "device": "cpu",
        "data": {"repeat": 1},
        "sfm": {"posed": True},
        "init": {"count": 3},
        "train": {"iterations": 4},
        "render": {"near": 0.01},
        "eval": {"split": "test"},
    }


def run(toy: Toy, run_dir: Path, dataset: Path, config: dict[str, Any] | None = None, **kwargs: Any) -> dict[str, str]:
    toy.calls.clear()
    return run_pipeline(toy.stages(), run_dir, config or base_config(), input_path=dataset, quiet=True, **kwargs)


# --- caching ------------------------------------------------------------------------------------


def test_first_run_runs_everything_and_second_run_skips_everything(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    run_dir = tmp_path / "run"
    status = run(toy, run_dir, dataset)
    assert status == {"data": "ran", "sfm": "not applicable", "init": "ran", "train": "ran", "eval": "ran"}
    assert run(toy, run_dir, dataset) == dict.fromkeys(ORDER, "cached")
    assert sum(toy.calls.values()) == 0
    assert not list(tmp_path.glob("run/*.tmp-*")) and not list(tmp_path.glob("run/*.work"))


def test_parameter_change_reruns_that_stage_and_downstream_only(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    run_dir = tmp_path / "run"
    config = base_config()
    run(toy, run_dir, dataset, config)
    config["train"]["iterations"] = 5
    assert run(toy, run_dir, dataset, config) == {**dict.fromkeys(ORDER, "cached"), "train": "ran", "eval": "ran"}
    config["render"]["near"] = 0.1  # train also depends on the render section
    assert set(run(toy, run_dir, dataset, config).values()) == {"cached", "ran"}
    assert toy.calls == {"train": 1, "eval": 1}
    config["seed"] = 1  # init declares the seed; the toy model ignores the primitives' content
    run(toy, run_dir, dataset, config)
    assert toy.calls == {"init": 1, "train": 1}  # same model bytes: eval stays cached
    config["init"]["count"] = 2
    run(toy, run_dir, dataset, config)
    assert toy.calls == {"init": 1, "train": 1, "eval": 1}
    assert read_manifest(run_dir / "init")["config"] == {"init": {"count": 2}, "seed": 1}


def test_unchanged_outputs_leave_downstream_cached(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    run_dir = tmp_path / "run"
    config = base_config()
    run(toy, run_dir, dataset, config)
    config["eval"]["split"] = "val"  # eval re-runs, nothing after it
    assert run(toy, run_dir, dataset, config)["eval"] == "ran"
    # the rule is content hashes: a stage that re-runs and writes the same bytes changes nothing downstream
    assert run(toy, run_dir, dataset, config, force={"init"}) == {**dict.fromkeys(ORDER, "cached"), "init": "ran"}


def test_changed_input_content_reruns_from_data(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    run_dir = tmp_path / "run"
    run(toy, run_dir, dataset)
    (dataset / "transforms.json").write_text("another scene")
    assert run(toy, run_dir, dataset)["data"] == "ran"
    assert toy.calls["train"] == 1


def test_run_dir_inside_the_dataset_does_not_invalidate_it(toy: Toy, dataset: Path) -> None:
    run(toy, dataset / "run", dataset)
    assert run(toy, dataset / "run", dataset) == dict.fromkeys(ORDER, "cached")


def test_deleted_output_reruns_its_stage(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    run_dir = tmp_path / "run"
    run(toy, run_dir, dataset)
    Run(run_dir).model.unlink()
    assert run(toy, run_dir, dataset) == {**dict.fromkeys(ORDER, "cached"), "train": "ran"}
    assert Run(run_dir).model.is_file()


def test_force_from_and_until(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    run_dir = tmp_path / "run"
    assert run(toy, run_dir, dataset, until_stage="init") == {"data": "ran", "sfm": "not applicable", "init": "ran"}
    assert not (run_dir / "train").exists()
    run(toy, run_dir, dataset)
    assert toy.calls == {"train": 1, "eval": 1}
    run(toy, run_dir, dataset, force={"train"})
    assert toy.calls == {"train": 1}
    run(toy, run_dir, dataset, from_stage="init")
    assert toy.calls == {"init": 1, "train": 1, "eval": 1}
    run(toy, run_dir, dataset, from_stage="init", until_stage="train")
    assert toy.calls == {"init": 1, "train": 1}


def test_stage_not_in_config_stages_cannot_be_skipped_silently(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    config = base_config()
    config["stages"] = ["data", "sfm", "train", "eval"]
    with pytest.raises(RadfieldError, match="train needs prims from stage init"):
        run(toy, tmp_path / "run", dataset, config)
    assert not (tmp_path / "run").exists()


# --- failures, kills and resume -------------------------------------------------------------------


def test_failing_stage_keeps_its_previous_output(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    run_dir = tmp_path / "run"
    config = base_config()
    run(toy, run_dir, dataset, config)
    model_before = Run(run_dir).model.read_text()
    manifest_before = read_manifest(run_dir / "train")
    config["train"]["iterations"] = 10
    toy.fail_train_at = 7
    with pytest.raises(KeyboardInterrupt):
        run(toy, run_dir, dataset, config)
    assert Run(run_dir).model.read_text() == model_before
    assert read_manifest(run_dir / "train") == manifest_before
    assert not list(run_dir.glob("*.tmp-*"))
    assert "eval" not in toy.calls
    assert sorted(p.name for p in (run_dir / "train.work").glob("*.ckpt")) == [f"{i}.ckpt" for i in range(7)]


def test_killed_training_resumes_from_its_checkpoint(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    reference = Toy()
    run(reference, tmp_path / "reference", dataset)

    run_dir = tmp_path / "run"
    toy.fail_train_at = 2
    with pytest.raises(KeyboardInterrupt):
        run(toy, run_dir, dataset)
    # a SIGKILL mid-swap would leave a complete-looking temporary directory: it must not be trusted
    leftover = run_dir / "train.tmp-dead"
    leftover.mkdir()
    (leftover / MODEL_FILE).write_text("half written")
    (leftover / "manifest.json").write_text(json.dumps({"done": True}))
    toy.fail_train_at = None
    assert run(toy, run_dir, dataset) == {**dict.fromkeys(ORDER, "cached"), "train": "ran", "eval": "ran"}
    assert toy.train_started_at == [0, 2]
    assert Run(run_dir).model.read_text() == Run(tmp_path / "reference").model.read_text()
    assert not leftover.exists() and not (run_dir / "train.work").exists()


def test_checkpoints_of_another_config_are_not_resumed(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    run_dir = tmp_path / "run"
    config = base_config()
    toy.fail_train_at = 2
    with pytest.raises(KeyboardInterrupt):
        run(toy, run_dir, dataset, config)
    toy.fail_train_at = None
    config["render"]["near"] = 0.5
    run(toy, run_dir, dataset, config)
    assert toy.train_started_at == [0, 0]


def test_force_discards_checkpoints(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    run_dir = tmp_path / "run"
    toy.fail_train_at = 2
    with pytest.raises(KeyboardInterrupt):
        run(toy, run_dir, dataset)
    toy.fail_train_at = None
    run(toy, run_dir, dataset, force={"train"})
    assert toy.train_started_at == [0, 0]
    # an interrupted --force leaves the previous result valid; its scratch goes on the next run
    toy.fail_train_at = 2
    with pytest.raises(KeyboardInterrupt):
        run(toy, run_dir, dataset, force={"train"})
    assert run(toy, run_dir, dataset)["train"] == "cached"
    assert not (run_dir / "train.work").exists()


def test_user_error_in_a_stage_names_the_stage(tmp_path: Path, dataset: Path) -> None:
    def broken(ctx: Context) -> None:
        raise RadfieldError("image 3.png is unreadable")

    stages = [Stage("data", broken, inputs=(INPUT,), outputs=("scene.txt",))]
    with pytest.raises(RadfieldError, match=r"^data: image 3.png is unreadable$"):
        run_pipeline(stages, tmp_path / "run", {"stages": ["data"]}, input_path=dataset, quiet=True)
    assert not (tmp_path / "run" / "data").exists()


def test_undeclared_seed_is_a_bug(tmp_path: Path) -> None:
    stages = [Stage("a", lambda ctx: {"seed": ctx.seed})]
    with pytest.raises(RuntimeError, match="without declaring 'seed'"):
        run_pipeline(stages, tmp_path / "run", {"stages": ["a"], "seed": 0}, quiet=True)


# --- run directory safety -------------------------------------------------------------------------


def test_folder_that_is_not_a_run_is_refused_untouched(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "holiday.jpg").write_text("precious")
    with pytest.raises(RadfieldError, match="is not a radfield run directory"):
        run(toy, folder, dataset)
    assert [p.name for p in folder.iterdir()] == ["holiday.jpg"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(RadfieldError, match="is not a directory"):
        run(toy, tmp_path / "file", dataset)
    (tmp_path / "empty").mkdir()
    assert run(toy, tmp_path / "empty", dataset)["data"] == "ran"


def test_other_input_is_refused_unless_forced(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    run_dir = tmp_path / "run"
    run(toy, run_dir, dataset)
    other = tmp_path / "other"
    other.mkdir()
    (other / "transforms.json").write_text("other scene")
    marker = (run_dir / "radfield-run.json").read_text()
    with pytest.raises(RadfieldError, match="was made from .*dataset, not .*other; .*--force data"):
        run(toy, run_dir, other)
    assert (run_dir / "radfield-run.json").read_text() == marker
    assert run(toy, run_dir, other, force={"data"})["data"] == "ran"
    assert run_info(run_dir)["input"] == str(other)


def test_bad_stage_names_are_refused_before_anything_is_written(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    cases: list[tuple[dict[str, Any], str]] = [
        ({"force": {"trian"}}, r"--force trian: no such stage \(did you mean train\?\)"),
        ({"from_stage": "evl"}, "--from evl: no such stage"),
        ({"from_stage": "eval", "until_stage": "init"}, "--from eval comes after --until init"),
    ]
    for kwargs, message in cases:
        with pytest.raises(RadfieldError, match=message):
            run(toy, tmp_path / "run", dataset, **kwargs)
    with pytest.raises(RadfieldError, match="input .* does not exist"):
        run(toy, tmp_path / "run", tmp_path / "missing")
    assert not (tmp_path / "run").exists()


def test_a_run_in_use_is_refused(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    run_dir = tmp_path / "run"
    run(toy, run_dir, dataset)
    with open(run_dir / ".lock") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        with pytest.raises(RadfieldError, match="in use by another radfield process"):
            run(toy, run_dir, dataset)


def test_resolved_config_is_saved(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    config = base_config()
    run(toy, tmp_path / "run", dataset, config)
    assert yaml.safe_load((tmp_path / "run" / "config.yaml").read_text()) == config


# --- info -------------------------------------------------------------------------------------------


def test_info_json_shape(toy: Toy, tmp_path: Path, dataset: Path) -> None:
    run_dir = tmp_path / "run"
    run(toy, run_dir, dataset, until_stage="train")
    info = run_info(run_dir)
    json.dumps(info)  # plain JSON
    assert set(info) == {"run", "input", "model", "normalization", "pending_checkpoint", "stages", "imported_from",
                         "edited_from", "edit", "artifacts"}
    assert info["pending_checkpoint"] is None
    assert info["model"] == str((run_dir / "train" / MODEL_FILE).resolve()) and info["normalization"] is None
    assert list(info["stages"]) == ORDER
    stages = info["stages"]
    assert stages["data"] == {"done": True, "seconds": stages["data"]["seconds"], "applicable": True, "images": 5}
    assert isinstance(stages["data"]["seconds"], float)
    assert stages["sfm"] == {"done": True, "seconds": stages["sfm"]["seconds"], "applicable": False,
                             "reason": "the dataset has poses"}
    assert stages["train"]["iterations"] == 4 and stages["train"]["train_psnr"] == 30.5
    assert stages["eval"] == {"done": False, "seconds": None, "applicable": None}
    text = format_info(info)
    for expected in ["data", "images=5", "n/a: the dataset has poses", "not run", str(Run(run_dir).model.name)]:
        assert expected in text


def test_info_refuses_other_folders(tmp_path: Path) -> None:
    with pytest.raises(RadfieldError, match="not a radfield run directory"):
        run_info(tmp_path)


# --- configuration ----------------------------------------------------------------------------------


def test_defaults_hold_every_section() -> None:
    config = load_config()
    assert config["stages"] == ["sfm", "data", "triangulate", "envelope", "tetra", "init", "train", "bind", "bake",
                                "eval"]
    assert {"seed", "device", "data", "sfm", "envelope", "tetra", "init", "train", "render", "bake", "eval"} <= set(config)
    assert config["train"]["max_primitives"] is None
    assert config["train"]["densify"]["grad_threshold"] == 5e-4  # exponent notation reads as a float
    # every call is a fresh copy: a run that edits its config cannot change the defaults of the next
    config["train"]["lr"]["means"] = -1.0
    config["stages"].append("eval")
    assert load_defaults()["train"]["lr"]["means"] == 1.6e-4 and load_config()["stages"] == config["stages"][:-1]


def _numeric_keys(config: dict, prefix: str = "") -> dict[str, Any]:
    """Every dotted key of `config` whose default is a number or a list of numbers (not a boolean),
    or null where the key takes an int (`int | None` in pipeline/schema.py)."""
    out = {}
    for name, value in config.items():
        key = f"{prefix}{name}"
        if isinstance(value, dict):
            out.update(_numeric_keys(value, key + "."))
        elif value is None and schema.keys()[key].type is int or isinstance(value, (int, float)) and not isinstance(value, bool) or \
                isinstance(value, list) and value and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            out[key] = value
    return out


def test_every_number_of_the_defaults_has_its_range() -> None:
    """Every numeric key of pipeline.yaml, and no other, has a range in pipeline/schema.py, and every
    default lies in its range (so a new key cannot go unchecked, and an out-of-range value is refused on set)."""
    numeric = _numeric_keys(load_defaults())
    ranges = {name: key.range for name, key in schema.keys().items() if key.range is not None}
    assert set(ranges) == set(numeric), (set(numeric) - set(ranges), set(ranges) - set(numeric))
    for key, default in numeric.items():
        for value in default if isinstance(default, list) else [] if default is None else [default]:
            assert ranges[key].holds(value), (key, value)


def test_overrides_parse_and_merge(tmp_path: Path) -> None:
    partial = tmp_path / "mine.yaml"
    partial.write_text("train:\n  iterations: 100\n  lr:\n    means: 1e-4\ndata:\n  background: [0, 0, 0]\neval:\n")
    config = load_config(
        partial,
        sets=["train.iterations=500", "train.max_primitives=2000", "render.omega0=20", "stages=[data, init, train]"],
        options={"seed": 3},
    )
    assert config["train"]["iterations"] == 500  # --set wins over the file
    assert config["train"]["lr"]["means"] == 1e-4 and config["train"]["lr"]["quats"] == 1e-3
    assert config["data"]["background"] == [0.0, 0.0, 0.0] and isinstance(config["data"]["background"][0], float)
    assert config["render"]["omega0"] == 20.0 and isinstance(config["render"]["omega0"], float)
    assert config["train"]["max_primitives"] == 2000 and config["seed"] == 3
    assert config["stages"] == ["data", "init", "train"]
    assert load_config(sets=["train.max_primitives=null"])["train"]["max_primitives"] is None
    assert load_config(sets=["data.downscale=null"])["data"]["downscale"] is None   # automatic (data.max_size)
    assert parse_set("data.background=[1, 0.5, 0]") == ("data.background", [1, 0.5, 0])


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("train.iteratons=5", r"unknown config key train.iteratons \(did you mean train.iterations\?\)"),
        ("iterations=5", r"unknown config key iterations \(did you mean train.iterations\?\)"),
        ("train.iterations=abc", r"train.iterations must be an integer, got \"abc\""),
        ("train.iterations=2.5", "train.iterations must be an integer, got 2.5"),
        ("train.iterations=true", "train.iterations must be an integer, got true"),
        ("data.test_every=null", "data.test_every must be an integer, got null"),
        ("train.max_primitives=1.5", "train.max_primitives must be an integer or null, got 1.5"),
        ("train.lambda_dssim=yes", "train.lambda_dssim must be a number, got true"),
        ("data.background=[1, 1]", r"data.background must be a list of 3 numbers, got \[1, 1\]"),
        ("data.background=[1, 1, x]", "data.background must be a list of 3 numbers"),
        ("train.primitive=nerf", "train.primitive must be one of neural, gaussian"),
        ("stages=[data, trian]", r"unknown entry \"trian\" \(did you mean train\?\)"),
        ("train=5", "train is a section"),
        ("train.lr.means.x=1", "train.lr.means is a value, not a section"),
        ("train.iterations", "--set expects key=value"),
        ("=5", "--set expects key=value"),
        ("data.background=[1,", "cannot parse the value of data.background"),
    ],
)
def test_bad_set_is_rejected_naming_the_key(override: str, message: str) -> None:
    with pytest.raises(RadfieldError, match=message) as error:
        load_config(sets=[override])
    assert "\n" not in str(error.value)


def test_bad_config_file_names_file_and_key(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("train:\n  densify:\n    evry: 10\n")
    suggestion = r"\(did you mean train.densify.every\?\)"
    with pytest.raises(RadfieldError, match=rf"{path}: unknown config key train.densify.evry {suggestion}"):
        load_config(path)
    path.write_text("train:\n  iterations: many\n")
    with pytest.raises(RadfieldError, match=rf"{path}: config key train.iterations must be an integer"):
        load_config(path)
    path.write_text("train: [1, 2]\n")
    with pytest.raises(RadfieldError, match="train is a section"):
        load_config(path)
    path.write_text("train: {iterations: [\n")
    with pytest.raises(RadfieldError, match=rf"^{path}: not valid YAML: expected .* \(line 2, column 1\)$"):
        load_config(path)
    with pytest.raises(RadfieldError, match="not found"):
        load_config(tmp_path / "missing.yaml")


def test_section_keeps_the_nesting_of_the_config() -> None:
    config = load_config()
    assert section(config, "eval") == {"eval": {"split": "test"}}
    both = section(config, ["train", "render", "seed"])
    assert set(both) == {"train", "render", "seed"} and both["render"] == config["render"]
    assert section(config, "train.lr") == {"train": {"lr": config["train"]["lr"]}}
    both["train"]["iterations"] = -1
    assert config["train"]["iterations"] == 3000


def test_save_resolved_round_trips(tmp_path: Path) -> None:
    config = load_config(sets=["train.densify.grad_threshold=2e-5"])
    save_resolved(config, tmp_path / "config.yaml")
    assert load_config(tmp_path / "config.yaml") == config
    assert [p.name for p in tmp_path.iterdir()] == ["config.yaml"]
