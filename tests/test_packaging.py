"""What a non-editable install carries: a wheel built from the project holds every file the fused
kernels are compiled from at first use (core/backends/csrc: a missing header makes their build fail and
training fall back to the slow torch path), the pipeline's defaults and the browser renderer's page."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_wheel_holds_every_kernel_source_and_the_defaults(tmp_path):
    source = tmp_path / "src"   # build from a copy: an in-tree build would write build/ into the checkout
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, source / name)
    shutil.copytree(ROOT / "radfield", source / "radfield", ignore=shutil.ignore_patterns("__pycache__"))
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation",
                            "--quiet", "--wheel-dir", str(tmp_path / "dist")], capture_output=True, text=True)
    assert built.returncode == 0, built.stderr[-2000:]
    (wheel,) = (tmp_path / "dist").glob("radfield-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    csrc = ROOT / "radfield" / "core" / "backends" / "csrc"
    kernel_files = {f"radfield/core/backends/csrc/{p.name}" for p in csrc.iterdir() if p.is_file()}
    assert any(name.endswith(".h") for name in kernel_files)   # the header the .cpp files include
    assert kernel_files - names == set()
    assert "radfield/pipeline.yaml" in names
    assets = ROOT / "radfield" / "delivery" / "web" / "assets"   # the browser renderer's page
    assert {f"radfield/delivery/web/assets/{p.name}" for p in assets.iterdir() if p.is_file()} - names == set()
    assert "radfield/delivery/web/assets/index.html" in names
