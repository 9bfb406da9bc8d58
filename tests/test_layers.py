"""The house's layering, declared once as import-linter contracts in pyproject.toml: the rooms in
their order (a room imports only rooms below it, lazily or not; siblings joined by | never import
each other), the core's rooms likewise, and no import cycle between the files or folders of any
folder. The contracts hold; a deliberately added upward import breaks them; and docs/design.md's
picture of the rooms is the contracts' own."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def lint_imports(cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    command = [str(Path(sys.executable).with_name("lint-imports")), "--no-cache"]
    return subprocess.run(command, cwd=cwd, env={**os.environ, **(env or {})}, capture_output=True, text=True,
                          timeout=300)


def test_the_import_contracts_hold():
    done = lint_imports(ROOT)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "3 kept, 0 broken" in done.stdout, done.stdout


def test_an_upward_import_breaks_them(tmp_path):
    """A kind that imports a stage (an arrow up from core to stages, and a cycle) is refused."""
    shutil.copytree(ROOT / "radfield", tmp_path / "radfield", ignore=shutil.ignore_patterns("__pycache__", "csrc"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    (tmp_path / "radfield/core/kinds/upward.py").write_text("def f():\n    from radfield.stages import train  # lazy: still an arrow\n")
    done = lint_imports(tmp_path, env={"PYTHONPATH": str(tmp_path)})
    assert done.returncode != 0, done.stdout
    assert "radfield's rooms, top down BROKEN" in done.stdout and "radfield.core.kinds.upward -> radfield.stages.train" in done.stdout


def contract_layers() -> dict[str, list[str]]:
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    return {c["id"]: c["layers"] for c in contracts if c["type"] == "layers"}


def picture(layers: list[str], container: str) -> list[str]:
    """The lines of design.md's picture of one contract: a layer a line, top down."""
    return [f"{container}." + "  |  ".join(part.strip() for part in layer.split("|")) for layer in layers]


def test_the_design_picture_is_the_contracts():
    text = (ROOT / "docs/design.md").read_text()
    block = text.split("<!-- rooms: drawn from pyproject.toml's import contracts -->")[1].split("```")[1]
    lines = [line.strip() for line in block.splitlines() if line.strip().startswith("radfield")]   # not the arrows
    layers = contract_layers()
    assert lines == [*picture(layers["rooms"], "radfield"), *picture(layers["core"], "radfield.core")]
