"""scripts/gpu_check.sh runs only on a lent GPU machine, with a few minutes of device time a session
and rarely a second try, so what can be checked without one is checked here: the shell parses,
every `radfield` command it runs parses (each option exists, each value has its type), the
Python its helpers call takes the arguments they pass, and its tuning script runs (in Triton's
interpreter)."""

from __future__ import annotations

import inspect
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import typer

from radfield.cli.main import _click_exceptions, app

UsageError = _click_exceptions().UsageError
IN_CI = os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")   # conftest.in_ci()

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "gpu_check.sh"
# the script's variables, as a run would set them ($W, its work folder, becomes a test's tmp_path)
VALUES = {"$W": "/tmp/w", "$DEVICE": "cuda", "$steps": "30000", "$1": "/tmp/w/run"}
COMMAND = re.compile(r"(?:^|\s)radfield\s+([a-z][a-z0-9-]*)\s(.*)")


def script_commands() -> list[tuple[int, list[str]]]:
    """(line number, argv after `radfield`) of every radfield command of the script."""
    found, lines = [], SCRIPT.read_text(encoding="utf-8").splitlines()
    for number, line in enumerate(lines, 1):
        following = number
        while line.endswith("\\") and following < len(lines):   # a command continued on the next line
            line, following = line[:-1] + lines[following], following + 1
        code = line.split(" #", 1)[0]
        match = COMMAND.search(code)
        if match is None or code.lstrip().startswith(("#", "radfield()")):
            continue
        # up to a pipe, a redirection or a background job's &
        text = re.split(r"\||\s\d*>|\s&(?:\s|$)", " ".join(match.groups()), maxsplit=1)[0]
        for name, value in VALUES.items():
            text = text.replace("${" + name[1:] + "}", value).replace(name, value)
        found.append((number, shlex.split(text)))
    return found


def test_the_script_parses():
    assert shutil.which("bash"), "bash is needed to check scripts/gpu_check.sh"
    result = subprocess.run(["bash", "-n", str(SCRIPT)], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_the_script_runs_every_benchmark_and_stage_it_reports():
    names = {argv[0] for _, argv in script_commands()}
    assert {"bench-render", "bench-train", "reconstruct", "render", "eval", "export", "info"} <= names


def parse(argv: list[str], folder: Path) -> None:
    """Parse `radfield ARGV` as the command would, short of running it (Click's make_context: a
    UsageError for an unknown command or option, a missing or extra value, a value of the wrong
    type); the folders it reads are made, empty, under `folder` first."""
    argv = [arg.replace(VALUES["$W"], str(folder)) for arg in argv]
    for before, arg in zip(argv, argv[1:]):
        if arg.startswith(str(folder)) and not before.startswith("-"):   # an input folder, not an output
            Path(arg).mkdir(parents=True, exist_ok=True)
    group = typer.main.get_command(app)
    with group.make_context("radfield", [], resilient_parsing=True) as parent:
        command = group.get_command(parent, argv[0])
        if command is None:
            raise UsageError(f"no command {argv[0]!r}")
        command.make_context(argv[0], argv[1:], parent=parent)


@pytest.mark.parametrize("number, argv", script_commands(), ids=lambda v: str(v) if isinstance(v, int) else v[0])
def test_every_radfield_command_of_the_script_parses(number, argv, tmp_path):
    try:
        parse(argv, tmp_path)
    except UsageError as error:
        pytest.fail(f"gpu_check.sh:{number}: radfield {shlex.join(argv)}: {error.format_message()}")


@pytest.mark.parametrize("argv", [["bench-render", "--primitive", "10"], ["bench-train", "--steps", "ten"],
                                  ["render", "/tmp/w/run", "extra", "-o", "frames"], ["bench-rendr"],
                                  ["eval", "/tmp/w/run", "-o"], ["reconstruct", "--no-cage"]])
def test_a_mistake_in_a_command_would_be_caught(argv, tmp_path):
    # the check above is a real parse: each of these fails it
    with pytest.raises(UsageError):
        parse(argv, tmp_path)


def test_the_scene_helper_calls_generate_scene_as_it_is():
    from radfield.demo.scenes import SCENES
    from radfield.demo.static import generate_scene

    text = SCRIPT.read_text(encoding="utf-8")
    call = re.search(r"generate_scene as g; g\('\$1', '\$2', (.*?)\)\"", text)
    assert call is not None, "the scene() helper no longer calls generate_scene"
    keywords = dict(part.strip().split("=") for part in call.group(1).split(","))
    inspect.signature(generate_scene).bind("studio", "/tmp/w", **keywords)
    for name in re.findall(r"\bscene (\w+) ", text):
        assert name in SCENES, f"gpu_check.sh generates an unknown scene {name!r}"


def test_the_tuning_script_times_every_variant_of_every_kind(tmp_path, monkeypatch):
    # in Triton's interpreter on a 16x16 view: the script's mechanics, not the options' effect
    from radfield.core.backends import gpu

    env = {**os.environ, "TRITON_INTERPRET": "1", "OMP_NUM_THREADS": "1"}
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    if not IN_CI and gpu.why_not() is not None:   # in CI it runs (and fails) regardless
        pytest.skip(f"the script cannot run the kernels here: {gpu.why_not()}")
    result = subprocess.run([sys.executable, str(SCRIPT.parent / "tune_kernels.py"), "--device", "cpu",
                             "--primitives", "20", "--size", "16", "--views", "1", "--repeats", "1"],
                            capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    rows = [line.split() for line in result.stdout.splitlines() if line.startswith("  ") and "variant" not in line]
    kinds = {row[-5] for row in rows}
    assert kinds == {"neural", "neural-hard", "gaussian"} and len(rows) == 6 * len(kinds), result.stdout
    assert all(float(value) >= 0 for row in rows for value in row[-4:]), result.stdout


def test_a_dry_run_blocks_the_packages_the_gpu_machine_lacks(tmp_path):
    """DRY_RUN=1: the script's own lines set PYTHONPATH so that every Python it starts fails to import
    the GPU machine's missing packages (here: pyvista, installed) and imports the others."""
    text = SCRIPT.read_text()
    block = text[text.index("MISSING="):text.index("\nfi\n", text.index("MISSING=")) + 4]
    probe = ("import importlib, sys\nfor name in sys.argv[1:]:\n    try:\n        importlib.import_module(name)\n"
             "        print(name, 'imports')\n    except ImportError as error:\n        print(name, error)\n")
    python = f"{shlex.quote(sys.executable)} -c {shlex.quote(probe)}"
    done = subprocess.run(["bash", "-c", f'set -u; W={shlex.quote(str(tmp_path))}; PYTHONPATH=; DRY_RUN=1\n{block}\n'
                           f'echo "device $DEVICE"; {python} pyvista numpy'], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "device cpu" in done.stdout
    assert "pyvista No module named 'pyvista' (gpu_check.sh WITHOUT)" in done.stdout, done.stdout
    assert "numpy imports" in done.stdout, done.stdout
