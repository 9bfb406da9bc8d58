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


class Killed(Exception):
    """Raised by `kill_and_resume`'s step hook: the training run is killed."""


def kill_and_resume(start, cameras, images, cfg, path, *, kill_at: int = 7, **run):
    """Train `start` with checkpoints written to `path`, kill the run after step `kill_at`, and
    resume it from its last checkpoint: (the checkpoint's state, the resumed run's final state)."""
    from radfield.core.train.trainer import load_checkpoint, save_checkpoint, train

    def kill(step, info):
        if step == kill_at:
            raise Killed

    with pytest.raises(Killed):
        train(start, cameras, images, cfg, **run, on_step=kill, checkpoint=lambda s: save_checkpoint(path, s))
    saved = load_checkpoint(path)
    return saved, train(start, cameras, images, cfg, **run, start_state=saved)


@pytest.fixture(name="kill_and_resume")
def kill_and_resume_fixture():
    """`kill_and_resume(start, cameras, images, cfg, path, kill_at=7, **run)` (see the function)."""
    return kill_and_resume
