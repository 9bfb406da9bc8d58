"""Fixtures and helpers shared by the test modules."""

import os
import sys
from pathlib import Path

import pytest

from radfield.cli.main import main

# the project's shared data, beside the worktree (/work/wt/shared -> /work/shared)
SHARED_DATASETS = Path(__file__).resolve().parents[2] / "shared" / "datasets"


def in_ci() -> bool:
    """Whether the tests run in CI (env CI=true), where a test may not skip what it checks."""
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


def shared_dataset(name: str, needs: str = "") -> Path:
    """The folder of ../shared/datasets/NAME (with its entry `needs`, e.g. "images", present).

    Missing: the test is skipped on a developer's machine, but FAILS under CI=true, so that CI
    cannot stay green by skipping the tests that need the data."""
    path = SHARED_DATASETS / name
    if not (path / needs).exists():
        message = f"shared dataset not found: {path / needs}"
        if in_ci():
            pytest.fail(f"{message} (CI=true: tests that need ../shared must not skip)", pytrace=False)
        pytest.skip(message)
    return path


@pytest.fixture(name="shared_dataset", scope="session")
def shared_dataset_fixture():
    """`shared_dataset(name, needs="")` for tests (see the function)."""
    return shared_dataset


@pytest.fixture(scope="session")
def fox() -> Path:
    """../shared/datasets/fox_small (photos in images/, nerfstudio poses with lens distortion)."""
    return shared_dataset("fox_small", "images")


@pytest.fixture
def cli(capsys):
    """Run `radfield ARGS` in this process: cli(*args) -> (exit code, stdout, stderr)."""

    def run(*args) -> tuple[int, str, str]:
        argv = sys.argv
        sys.argv = ["radfield", *map(str, args)]
        try:
            main()
            code = 0
        except SystemExit as exit_:
            code = exit_.code or 0
        finally:
            sys.argv = argv
        out, err = capsys.readouterr()
        return code, out, err

    return run
