"""Sizes and fidelity of every export format (issue 41): for each run, `radfield export` to every
format that writes a model, and a markdown table of each file's bytes, the export's time, and the
file read back and rendered at the run's test cameras: PSNR against the run's own render (its
model drawn as `radfield render RUN` draws it, before the PNG's 8 bits) and against the dataset's
test photos (held-out, as the eval stage scores the run).

    radfield demo-scene blobs -o demo/blobs
    OMP_NUM_THREADS=1 radfield reconstruct demo/blobs -o neural
    OMP_NUM_THREADS=1 radfield reconstruct demo/blobs -o gauss --primitive gaussian
    OMP_NUM_THREADS=1 .venv/bin/python scripts/export_table.py neural gauss -o exports

The first row of a run is its own model file (train/model.safetensors, the reference). The 3DGS
files are read by radfield.model_formats.read; web's model.bin is decoded as the page decodes it
(radfield.delivery.web.model_bin.decoded). Exports run one at a time with their defaults (a
neural run is refined into Gaussians); time is the command's wall clock and CPU (user + system) of
the whole `radfield export` process, its start-up and its own read-back check included. PSNR is
the mean over the test views of each view's PSNR (renders clamped to [0, 1]), capped at 99 dB as
tests/test_model_formats.py caps it.
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from radfield import model_formats
from radfield.core.render.antialias import render_model
from radfield.datasets.scene import load_split
from radfield.delivery.web import model_bin
from radfield.model_file import load_model
from radfield.pipeline.config import load_config
from radfield.run import Run

FORMATS = {"ply-3dgs": ".ply", "splat": ".splat", "spz": ".spz", "glb": ".glb", "web": ".web"}
CAP = 99.0


def export(run: Path, fmt: str, out: Path) -> tuple[str, float, float]:
    """`radfield export run -f fmt -o out`: (its line, wall seconds, CPU seconds)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "radfield", "export", str(run), "-f", fmt, "-o", str(out), "-q",
                           "--force"], check=True, capture_output=True, text=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return done.stdout.strip().splitlines()[0], wall, cpu


def mean_psnr(images, references) -> float:
    values = [min(CAP, float(-10 * torch.log10(((a - b) ** 2).mean().clamp_min(1e-30))))
              for a, b in zip(images, references)]
    return float(np.mean(values))


def table_rows(run: Path, out: Path):
    config = load_config(run / "config.yaml")
    background, near = tuple(config["data"]["background"]), config["render"]["near"]
    test = load_split(Path(Run(run).dataset()), "test", config["data"])
    photos = [test.load_image(k)[0] for k in range(len(test))]
    model_path = Run(run).model   # what `radfield render RUN` draws
    reference = load_model(model_path)

    def draw(model):
        with torch.no_grad():
            return [render_model(model, c, background=background, near=near).color.clamp(0, 1) for c in test.cameras]

    own = draw(reference)
    files = [("model.safetensors", model_path, model_formats.read(model_path), None)]
    for fmt, suffix in FORMATS.items():
        path = out / f"{run.name}{suffix}"
        line, wall, cpu = export(run, fmt, path)
        print(f"{run.name} {fmt}: {line} [{wall:.1f} s wall, {cpu:.1f} s CPU]", file=sys.stderr)
        if fmt == "web":
            path = path / "model.bin"
            model = model_bin.decoded(reference, path.read_bytes())
        else:
            model = model_formats.read(path)
        files.append((fmt, path, model, (wall, cpu)))
    run_held_out = mean_psnr(own, photos)
    for fmt, path, model, times in files:
        images = draw(model)
        held_out = mean_psnr(images, photos)
        yield (run.name, fmt, f"{path.stat().st_size:,}", f"{len(model):,}",
               "—" if times is None else f"{times[0]:.1f} / {times[1]:.1f}",
               fmt_db(mean_psnr(images, own)), f"{held_out:.2f} ({round(held_out - run_held_out, 2) + 0.0:+.2f})")


def fmt_db(value: float) -> str:
    return "exact" if value >= CAP else f"{value:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run directories (radfield reconstruct)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="folder for the exported files")
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    header = ("run", "format", "bytes", "primitives", "export s (wall / CPU)", "PSNR against the run's render",
              "held-out PSNR (Δ to the run)")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for run in args.runs:
        for row in table_rows(run, args.output):
            print("| " + " | ".join(row) + " |", flush=True)


if __name__ == "__main__":
    main()
