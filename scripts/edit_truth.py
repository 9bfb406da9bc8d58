"""Edits against the truth (issue #28): alpha and rgb PSNR of edited reconstructions against
`demo-scene NAME --deform MAP` renders of the truly deformed shapes, through the same cameras.

    radfield demo-scene objects -o REST --size 128 --test-views 20
    radfield demo-scene objects --deform twist -o TWIST --size 128 --test-views 20     # also bend, squash
    OMP_NUM_THREADS=1 radfield reconstruct REST -o RUN
    OMP_NUM_THREADS=1 .venv/bin/python scripts/edit_truth.py RUN REST TWIST BEND SQUASH -o OUT \
        [--modes tet,centre,smooth,map] [--radfield /tmp/oldrf.sh] [--preserve-opacity] \
        [--cage-file] [--cage COARSE.npz | --box-cage 4]

For every deformed dataset and gradient mode it runs `RADFIELD edit RUN --spec S -o OUT/<map>-<mode>`
(S: the dataset's deform.yaml with `gradient: <mode>`; the affine squash goes through its cage,
`deform: {cage: ...}` with the run's cage vertices moved by A, which every version of the editor
takes, and also through deform.yaml itself as the row "<map>-spec"). With --cage-file the twist and
bend also go through a cage file, as a user's cage deformed in another tool comes back (issue 41):
the run's cage vertices moved by the dataset's exact map (radfield/demo/deformations.py), rows
"file-<mode>" for the cage modes. --cage FILE replaces the run's cage in every edit (`radfield edit
--cage`, the primitives bound to it afresh; the cage files are then that cage moved), e.g. a coarser
cage to see how the cage's resolution matters; --box-cage N does so with a regular N³ box cage
around the run's cage. It renders the edited model with
the deformed dataset's test cameras and prints, per row, alpha PSNR and rgb PSNR (rgb composited on
the dataset's background, as `radfield eval`) over the test views; the first row is the unedited
reconstruction against the undeformed truth. A mode the editor refuses prints its one-line error.
Rendering uses this checkout's renderer for every row (the edited model files of an older editor
are plain model files).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
import yaml

from radfield.core.geometry.cage import read_cage, write_cage
from radfield.core.render.antialias import render_model
from radfield.datasets.readers import load_dataset
from radfield.demo.deformations import Deformation
from radfield.edit.field import box_cage
from radfield.edit.source import load_source


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else -10 * np.log10(mse)


def score(prims, dataset) -> tuple[float, float]:
    """Mean over the views of alpha PSNR and rgb PSNR (on the dataset's background)."""
    alphas, rgbs = [], []
    background = torch.tensor(dataset.background, dtype=torch.float32)
    with torch.no_grad():
        for i, camera in enumerate(dataset.cameras):
            rgb, alpha = dataset.load_image(i)
            out = render_model(prims, camera, background=background)
            alphas.append(psnr(out.alpha.numpy(), alpha.numpy()))
            rgbs.append(psnr(out.color.clamp(0, 1).numpy(), rgb.numpy()))
    return float(np.mean(alphas)), float(np.mean(rgbs))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="reconstruction of the undeformed scene")
    parser.add_argument("rest", type=Path, help="the undeformed demo scene (its test views)")
    parser.add_argument("deformed", type=Path, nargs="+", help="demo scenes written with --deform")
    parser.add_argument("-o", "--output", type=Path, required=True, help="folder for the edited runs (created)")
    parser.add_argument("--modes", default="tet,centre,smooth,map", help="gradient modes to try (comma-separated)")
    parser.add_argument("--radfield", default=str(Path(sys.executable).with_name("radfield")), help="the radfield executable that edits")
    parser.add_argument("--preserve-opacity", action="store_true", help="pass --preserve-opacity to every edit")
    parser.add_argument("--cage-file", action="store_true", help="also edit the twist and bend through a cage file (rows file-<mode>)")
    parser.add_argument("--cage", type=Path, help="replace the run's cage with this cage file in every edit (radfield edit --cage)")
    parser.add_argument("--box-cage", type=int, metavar="N", help="as --cage with a regular N³ box cage 0.05 beyond the "
                        "run's cage's bounding box (written to OUT/box-cage), a coarse cage")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=False)

    source = load_source(args.run)
    if args.box_cage:
        lo, hi = source.cage_vertices.min(0) - 0.05, source.cage_vertices.max(0) + 0.05
        write_cage(args.output / "box-cage", *box_cage(lo, hi, args.box_cage))
        args.cage = args.output / "box-cage" / "cage.npz"
    cage_vertices, cage_tets = read_cage(args.cage) if args.cage else (source.cage_vertices, source.cage_tets)
    cage_modes = [mode for mode in args.modes.split(",") if mode != "map"]   # a cage file has no closed-form map
    rows = []
    alpha, rgb = score(source.prims, load_dataset(args.rest, split="test"))
    rows.append({"edit": "unedited", "mode": "-", "alpha_psnr": alpha, "rgb_psnr": rgb})
    print(f"{'edit':10s} {'mode':12s} {'alpha PSNR':>10s} {'rgb PSNR':>9s}")
    print(f"{'unedited':10s} {'-':12s} {alpha:10.2f} {rgb:9.2f}", flush=True)
    for folder in args.deformed:
        info = json.loads((folder / "scene.json").read_text())["deform"]
        name, op = info["name"], info["edit_spec"]
        truth = load_dataset(folder, split="test")
        # the cage moved by the dataset's exact map, as a cage deformed in another tool comes back
        exact = Deformation(info["kind"], info.get("degrees_per_unit", 0.0), tuple(map(tuple, info["matrix"])))
        write_cage(args.output / f"{name}-cage", exact.forward(cage_vertices), cage_tets)
        cage = (args.output / f"{name}-cage" / "cage.npz").resolve()
        by_file = [(mode, {"deform": {"cage": str(cage), "gradient": mode}}) for mode in cage_modes]
        if name == "squash":
            jobs = by_file + [("spec", op)]
        else:
            (kind, body), = op.items()
            jobs = [(mode, {kind: {**body, "gradient": mode}}) for mode in args.modes.split(",")]
            if args.cage_file:
                jobs += [(f"file-{mode}", operation) for mode, operation in by_file]
        for mode, operation in jobs:
            spec = args.output / f"{name}-{mode}.yaml"
            spec.write_text(yaml.safe_dump({"operations": [operation]}, default_flow_style=None))
            out = args.output / f"{name}-{mode}"
            command = [args.radfield, "edit", str(args.run), "--spec", str(spec), "-o", str(out), "--quiet"]
            if args.preserve_opacity:
                command.append("--preserve-opacity")
            if args.cage:
                command += ["--cage", str(args.cage.resolve())]
            done = subprocess.run(command, capture_output=True, text=True)
            if done.returncode != 0:
                line = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
                rows.append({"edit": name, "mode": mode, "error": line})
                print(f"{name:10s} {mode:12s} refused: {line}", flush=True)
                continue
            alpha, rgb = score(load_source(out).prims, truth)
            rows.append({"edit": name, "mode": mode, "alpha_psnr": alpha, "rgb_psnr": rgb})
            print(f"{name:10s} {mode:12s} {alpha:10.2f} {rgb:9.2f}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
