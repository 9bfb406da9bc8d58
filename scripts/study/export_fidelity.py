"""Export fidelity (issue 28): a 3DGS PLY rendered by the independent numpy splatter of
tests/test_export.py on a run's test views, against the photos and against the run's own renders.

    python scripts/study/export_fidelity.py RUN PLY [PLY ...]

prints, per PLY, the held-out PSNR of the splatted PLY (mean over the test views, as the eval
stage), next to the run's own held-out PSNR (RUN/eval/metrics.json)."""

from __future__ import annotations

import importlib.util
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def splatter():
    spec = importlib.util.spec_from_file_location("test_export", ROOT / "tests" / "test_export.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.splat_numpy


def psnr(a, b):
    return float(-10 * np.log10(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2)))


def main(run: Path, plys: list[Path]) -> None:
    from radfield.datasets.scene import load_scene

    splat = splatter()
    scene = load_scene(run / "data" / "scene.json")
    cameras = scene.test_cameras
    images = scene.test_images().numpy()
    background = scene.background
    own = json.loads((run / "eval" / "metrics.json").read_text())["psnr"]
    print(f"{run}: run held-out {own:.2f} dB ({len(cameras)} test views)")
    for ply in plys:
        t = time.perf_counter()
        values = [psnr(splat(ply, c, background).clip(0, 1), img) for c, img in zip(cameras, images)]
        print(f"  {ply}: splatted held-out {np.mean(values):.2f} dB ({np.mean(values) - own:+.2f} dB; "
              f"{time.perf_counter() - t:.0f} s to splat)")


if __name__ == "__main__":
    main(Path(sys.argv[1]), [Path(p) for p in sys.argv[2:]])
