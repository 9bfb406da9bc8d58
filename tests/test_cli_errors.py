"""Every user mistake on every command is one line `radfield: error: …` and exit code 1, also the
ones Click finds while parsing (wrong option types, missing or unknown options and commands)."""

import pytest


@pytest.mark.parametrize("args, message", [
    (["reconstruct", "data", "-o", "run", "--iterations", "many"], "Invalid value for '--iterations'"),
    (["reconstruct", "data"], "Missing option '--output'"),
    (["reconstruct", "data", "-o", "run", "--frobnicate"], "No such option: --frobnicate"),
    (["eval", "run", "-o", "report", "--downscale", "half"], "Invalid value for '--downscale'"),
    (["eval", "run", "-o"], "Option '-o' requires an argument"),
    (["info"], "Missing argument 'RUN'"),
    (["render", "model.safetensors", "-o", "out", "--near", "close"], "Invalid value for '--near'"),
    (["bench-render", "--primitives", "lots"], "Invalid value for '--primitives'"),
    (["demo-scene", "blobs", "-o", "scene", "--size", "big"], "Invalid value for '--size'"),
    (["demo-scene", "blobs", "-o", "scene", "--workers", "0"], "--workers must be at least 1, got 0"),
    (["demo-scene", "smoke", "-o", "scene", "--workers", "4"], "demo-scene smoke: --workers is for the static scenes"),
    (["no-such-command"], "No such command 'no-such-command'"),
])
def test_usage_errors_are_one_line_and_exit_1(cli, tmp_path, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    code, out, err = cli(*args)
    assert code == 1 and out == ""
    assert err.startswith("radfield: error: ") and message in err and err.count("\n") == 1, err
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_work_errors_are_one_line_too(cli, tmp_path):
    code, _, err = cli("info", tmp_path)
    assert code == 1 and err == f"radfield: error: {tmp_path} is not a radfield run directory\n"
    code, _, err = cli("render", tmp_path / "model.safetensors", "-o", tmp_path / "out")
    assert code == 1 and "no such model file or run directory" in err and err.count("\n") == 1


def test_help_and_version_still_exit_0(cli):
    code, out, _ = cli("render", "--help")
    assert code == 0 and "MODEL_OR_RUN" in out and "--dataset" in out
    code, out, _ = cli("--version")
    assert code == 0 and out.startswith("radfield ")
    code, out, _ = cli()  # no command: the overview
    assert code == 0 and "reconstruct" in out


def test_a_click_without_no_args_is_help_error_still_gives_one_line(cli, monkeypatch):
    # Click < 8.2 (with Typer < 0.20, which pyproject allows) has no NoArgsIsHelpError: the entry
    # point's `except` must not fail on it when another error passes (an AttributeError there, once)
    from radfield.cli.main import _click_exceptions

    real = _click_exceptions()
    monkeypatch.delattr(real, "NoArgsIsHelpError")
    assert issubclass(_click_exceptions().NoArgsIsHelpError, Exception)
    code, out, err = cli("reconstruct", "data", "-o", "run", "--frobnicate")
    assert code == 1 and out == "" and err.startswith("radfield: error: No such option: --frobnicate"), err


@pytest.mark.parametrize("tensor, row, value, message", [
    ("log_scales", 3, 100.0, "tensor 'log_scales' is out of range at primitive 3"),
    ("means", 1, float("inf"), "tensor 'means' holds 3 NaN/Inf values (first at primitive 1)"),
    ("quats", 2, 0.0, "tensor 'quats' has all-zero rows"),
])
def test_a_model_with_values_out_of_range_is_one_line_on_every_reader(cli, tmp_path_factory, tmp_path, tensor, row,
                                                                      value, message):
    """Such a model (log_scales = 100) loaded and rendered silently as background (issue #28)."""
    from radfield.core.kinds import random_neural
    from radfield.demo.static import generate_scene
    from radfield.model_file import save_model

    data = tmp_path_factory.getbasetemp() / "tiny-blobs"
    if not data.exists():
        generate_scene("blobs", data, n_train=2, n_test=1, size=16, seed=0)

    prims = random_neural(5, sh_degree=1)
    getattr(prims, tensor)[row] = value
    model = tmp_path / "bad.safetensors"
    save_model(model, prims)
    for args in (["render", model, "-d", data, "-o", tmp_path / "out"], ["export", model, "-f", "ply-3dgs", "-o", tmp_path / "out.ply"]):
        code, out, err = cli(*args)
        assert code == 1 and err.startswith("radfield: error: ") and err.count("\n") == 1, err
        assert message in err and str(model) in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.safetensors"]   # nothing written


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory, run_radfield):
    """A dataset and a finished run of it, both tiny."""
    from radfield.demo.static import generate_scene

    root = tmp_path_factory.mktemp("tiny")
    data = generate_scene("blobs", root / "blobs", n_train=4, n_test=1, size=16, seed=0)
    assert run_radfield("reconstruct", data, "-o", root / "run", "-q", "--iterations", "5", "--no-cage",
                        "--set", "init.num_points=50") == 0
    return data, root / "run"


# Out-of-range numbers of every verb's own options (the pipeline's keys: tests/test_stages.py).
BAD_NUMBERS = [
    ("render", "--downscale", "0"), ("render", "--near", "0"), ("render", "--near", "nan"), ("render", "--orbit", "-2"),
    ("render", "--elevation", "95"), ("render", "--elevation", "inf"), ("render", "--fps", "0"), ("render", "--time", "2"),
    ("render", "--light-intensity", "-1"), ("render", "--light-orbit", "-1"), ("render", "--camera", "-1"),
    ("eval", "--downscale", "0"),
    ("bake", "--min-weight", "1.5"), ("bake", "--downscale", "-1"),
    ("animate", "--elevation", "-91"), ("animate", "--downscale", "0"),
    ("animate", "--fps", "-3"), ("animate", "--split-threshold", "-1"), ("animate", "--split-threshold", "nan"),
    ("edit", "--scale", "0"), ("edit", "--scale", "-2"), ("edit", "--scale", "inf"), ("edit", "--split-threshold", "-0.5"),
    ("edit", "--seed", "-1"),
    ("export", "--components", "0"), ("export", "--refine", "-1"), ("export", "--time", "-0.1"),
    ("export", "--light-intensity", "0"),
    ("view", "--port", "-1"), ("view", "--port", "70000"), ("view", "--resolution", "8"), ("view", "--moving-downscale", "0"),
    ("view", "--time", "1.5"),
    ("demo-scene", "--size", "0"), ("demo-scene", "--train-views", "0"), ("demo-scene", "--test-views", "-1"),
    ("demo-scene", "--seed", "-1"), ("demo-scene", "--times", "0"), ("demo-scene", "--lights", "0"),
    ("bench-render", "--primitives", "0"), ("bench-train", "--steps", "0"), ("bench-quality", "--iterations", "0"),
    ("bench-dist", "--size", "0"), ("bench-startup", "--repeats", "0"),
]


def _verb_args(verb, data, run, out):
    return {"render": ["render", run, "-o", out], "eval": ["eval", run, "-o", out], "bake": ["bake", run, "-o", out / "b.safetensors"],
            "animate": ["animate", run, "-o", out, "--simulate", out.parent / "sim.yaml"], "edit": ["edit", run, "-o", out, "--rotate", "0,0,10"],
            "export": ["export", run, "-f", "ply-3dgs", "-o", out / "m.ply"], "view": ["view", run],
            "demo-scene": ["demo-scene", "blobs", "-o", out], "bench-render": ["bench-render"],
            "bench-train": ["bench-train"], "bench-quality": ["bench-quality", data, "-o", out],
            "bench-dist": ["bench-dist"], "bench-startup": ["bench-startup"]}[verb]


@pytest.mark.parametrize("verb, option, value", BAD_NUMBERS, ids=[" ".join(case) for case in BAD_NUMBERS])
def test_an_out_of_range_number_is_one_line_before_any_work(cli, tiny_run, tmp_path, verb, option, value):
    data, run = tiny_run
    out = tmp_path / "out"
    before = sorted(p.name for p in run.rglob("*"))
    code, stdout, err = cli(*_verb_args(verb, data, run, out), option, value)
    assert code == 1 and stdout == "" and err.startswith("radfield: error: ") and err.count("\n") == 1, err
    assert option in err, err
    assert not out.exists() and sorted(p.name for p in run.rglob("*")) == before


def test_bench_quality_takes_the_kinds_the_registry_has(cli, tiny_run, tmp_path):
    """bench-quality's --kinds are the registry's unconditioned kinds: a conditioned one (it needs a
    time) or an unknown one is one line naming the choices, before any run."""
    data, _ = tiny_run
    for bad in ("neural-dynamic", "neural,splats"):
        code, stdout, err = cli("bench-quality", data, "-o", tmp_path / "out", "--kinds", bad)
        assert code == 1 and err.startswith("radfield: error: --kinds takes neural, gaussian") and err.count("\n") == 1, err
        assert not (tmp_path / "out").exists()
