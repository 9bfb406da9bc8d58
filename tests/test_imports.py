"""Imports where they are used: `radfield --help` and every `radfield COMMAND --help` import no
heavy library, and render, eval, export and a --no-cage reconstruction of a posed dataset work on
a machine without the geometry libraries (pymeshlab, pyvista, pycolmap, pytetwild,
fast_simplification), simulated by a meta-path hook that makes importing them fail.

Both run in fresh interpreters (subprocesses): what a process has imported is only meaningful
from its start. Start-up times are `radfield bench-startup`'s figures, not a test."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from radfield.demo.static import generate_scene

GEOMETRY = ("pymeshlab", "pyvista", "pycolmap", "pytetwild", "fast_simplification")
HEAVY = ("torch", "numpy", "scipy", "skimage", "meshio", "OpenImageIO", "cv2", "viser", "matplotlib", *GEOMETRY)

# Makes `import NAME` (and NAME.anything) of the BLOCKED modules raise ImportError, as on a machine
# that lacks them; then runs `radfield ARGV` and exits with its status.
BLOCKING_RADFIELD = textwrap.dedent("""
    import importlib.abc, sys

    BLOCKED = set(sys.argv[1].split(","))

    class Missing(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.partition(".")[0] in BLOCKED:
                raise ImportError(f"No module named {name!r} (blocked by tests/test_imports.py)", name=name)
            return None

    sys.meta_path.insert(0, Missing())
    sys.argv = ["radfield", *sys.argv[2:]]
    from radfield.cli.main import main
    main()
""")

# Runs `radfield ARGS --help` for the root and for every command in this one process and prints
# the top-level names of the modules that were imported.
HELP_IMPORTS = textwrap.dedent("""
    import json, sys
    from radfield.cli.main import app, command_names, main

    for args in [["--help"]] + [[name, "--help"] for name in command_names(app)]:
        sys.argv = ["radfield", *args]
        try:
            main()
        except SystemExit as exit_:
            assert not exit_.code, (args, exit_.code)
    print(json.dumps({"commands": command_names(app), "modules": sorted({m.partition(".")[0] for m in sys.modules})}))
""")

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "RADFIELD_KERNELS": "torch", "COLUMNS": "100"}


def without_geometry(*args, timeout=600) -> subprocess.CompletedProcess:
    """`radfield ARGS` in a fresh interpreter in which the GEOMETRY libraries cannot be imported."""
    return subprocess.run([sys.executable, "-c", BLOCKING_RADFIELD, ",".join(GEOMETRY), *map(str, args)],
                          env=ENV, capture_output=True, text=True, timeout=timeout)


def test_help_imports_no_heavy_library():
    done = subprocess.run([sys.executable, "-c", HELP_IMPORTS], env=ENV, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert {"reconstruct", "render", "eval", "export", "edit", "bench-startup"} <= set(report["commands"])
    assert [name for name in HEAVY if name in report["modules"]] == []
    assert "radfield" in report["modules"]   # the check looked at the process that ran the commands


def test_the_hook_blocks_the_geometry_libraries():
    """The hook the next test relies on does make these imports fail (else it would prove nothing)."""
    for name in GEOMETRY:
        done = subprocess.run([sys.executable, "-c", BLOCKING_RADFIELD.replace(
            "from radfield.cli.main import main\nmain()", f"import {name}"), name], env=ENV, capture_output=True,
            text=True, timeout=120)
        assert done.returncode != 0 and "blocked by tests/test_imports.py" in done.stderr, (name, done.stderr)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A posed NeRF-synthetic dataset without its mesh.ply, which pyvista writes: the GPU machine
    that runs this file (scripts/gpu_check.sh) has no pyvista either."""
    return generate_scene("blobs", tmp_path_factory.mktemp("imports") / "blobs", n_train=4, n_test=2, size=24,
                          mesh=False)


def test_posed_dataset_without_geometry_libraries(scene, tmp_path):
    run = tmp_path / "run"
    done = without_geometry("reconstruct", scene, "-o", run, "--no-cage", "--iterations", "4", "--quiet",
                            "--set", "init.num_points=60", "--set", "train.eval_every=0")
    assert done.returncode == 0, done.stderr
    assert "eval ran" in done.stdout and (run / "train" / "model.safetensors").is_file()
    assert "triangulate not applicable" in done.stdout   # no pycolmap: the start is random

    done = without_geometry("render", run, "-o", tmp_path / "frames", "-q")
    assert done.returncode == 0, done.stderr
    assert len(list((tmp_path / "frames").glob("*.png"))) == 2

    done = without_geometry("eval", run, "-o", tmp_path / "report", "-q")
    assert done.returncode == 0, done.stderr
    assert json.loads((tmp_path / "report" / "metrics.json").read_text())["views"] == 2

    done = without_geometry("export", run, "-f", "ply-3dgs", "-o", tmp_path / "model.ply", "--refine", "2", "-q")
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "model.ply").stat().st_size > 0
    done = without_geometry("export", run, "-f", "cameras", "-o", tmp_path / "transforms.json")
    assert done.returncode == 0, done.stderr
    assert len(json.loads((tmp_path / "transforms.json").read_text())["frames"]) == 6
