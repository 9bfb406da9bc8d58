"""Fixtures shared by the test modules."""

import sys

import pytest

from radfield.cli.main import main


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
