"""Evidence for the editor (not a test): writes a slow twist of a run's cage as cage frames for
`radfield animate`, and times renders of the original and the most twisted model from one camera.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/edit_evidence.py RUN OUT [--frames 60] [--degrees 45]
    OMP_NUM_THREADS=1 .venv/bin/radfield animate RUN --cages OUT/cages -o OUT/anim

The twist turns about the vertical axis through the cage's centre: the top of the cage turns by
t·DEGREES relative to the bottom at frame t ∈ [0, 1].
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch

from radfield.edit.source import load_source
from radfield.core.geometry.cage import write_cage
from radfield.core.render.rasterize import render
from radfield.datasets.readers import load_dataset
from radfield.edit.affine import deform_field
from radfield.edit.warp import axis_rotation
from radfield.run import Run


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("run", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--degrees", type=float, default=45.0)
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    fld = load_source(args.run)
    v = fld.cage_vertices
    centre = 0.5 * (v.min(0) + v.max(0))
    height = v[:, 2].max() - v[:, 2].min()
    axis = np.array([0.0, 0.0, 1.0])
    poses = []
    for i in range(args.frames):
        rate = math.radians(args.degrees * i / max(args.frames - 1, 1)) / height
        rel = v - centre
        new = centre + np.einsum("nij,nj->ni", axis_rotation(axis, rate * (rel[:, 2] - rel[:, 2].min())), rel)
        write_cage(args.out / "cages" / f"frame_{i:04d}", new, fld.cage_tets)
        poses.append(new)
    print(f"wrote {args.frames} twist frames (0 -> {args.degrees} degrees over the cage's height {height:.3f}) to {args.out / 'cages'}")

    twisted = deform_field(fld, poses[-1])
    print(f"most twisted frame: {twisted.notes[-1]}")
    cam = load_dataset(Run(args.run).dataset(), split="test").cameras[0]
    models = {"original": fld.prims, "twisted": twisted.prims}
    times = {name: [] for name in models}
    with torch.no_grad():
        for prims in models.values():
            render(prims, cam)  # warm-up
        for _ in range(args.repeats):  # interleaved, so machine load affects both alike
            for name, prims in models.items():
                start = time.perf_counter()
                render(prims, cam)
                times[name].append(time.perf_counter() - start)
    for name, t in times.items():
        t = 1e3 * np.array(t)
        print(f"{name:9s} {len(models[name].means)} primitives: render {np.median(t):.1f} ms/frame median "
              f"(mean {t.mean():.1f}, min {t.min():.1f}) over {len(t)} renders of {cam.width}x{cam.height}")


if __name__ == "__main__":
    main()
