"""Neural primitives against 3D Gaussians at equal primitive budgets (the paper's protocol).

For each scene, kind (neural, gaussian) and budget (a number, or "none" for densification without
a cap), runs `radfield reconstruct` into OUT/<scene>-<kind>-<budget> and prints one Markdown table
of held-out PSNR/SSIM, primitive and parameter counts and training time. Jobs run two at a time
with one thread each (two busy OpenMP pools on two cores slow each other down badly).

    .venv/bin/python scripts/compare_budgets.py OUT --scene blobs=demo/blobs \
        --scene lego=../shared/datasets/lego_small:4 --budgets 500 2000 none --iterations 2000

A scene is NAME=PATH[:DOWNSCALE]. Runs already complete are reused (the pipeline's cache).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

RADFIELD = [sys.executable, "-m", "radfield"]


def run_one(out: Path, name: str, path: str, downscale: int, kind: str, budget: str, iterations: int) -> dict:
    run = out / f"{name}-{kind}-{budget}"
    args = [*RADFIELD, "reconstruct", path, "-o", str(run), "--primitive", kind, "--iterations", str(iterations),
            "--downscale", str(downscale), "--quiet",
            "--set", f"train.densify.stop={int(iterations * 0.75)}",
            "--set", f"train.densify.start={min(500, iterations // 5)}"]
    if budget != "none":
        args += ["--max-primitives", budget]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(args, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        return {"scene": name, "kind": kind, "budget": budget, "error": proc.stderr.strip().splitlines()[-1:]}
    info = json.loads(subprocess.run([*RADFIELD, "info", str(run), "--json"], capture_output=True, text=True,
                                     check=True).stdout)
    train, evaluation = info["stages"]["train"], info["stages"]["eval"]
    return {"scene": name, "kind": kind, "budget": budget, "psnr": evaluation["psnr"], "ssim": evaluation["ssim"],
            "primitives": train["primitives"], "params": train["params"], "train_seconds": train["seconds"],
            "train_psnr": train["train_psnr"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path)
    parser.add_argument("--scene", action="append", required=True, help="NAME=PATH[:DOWNSCALE]")
    parser.add_argument("--budgets", nargs="+", default=["500", "2000", "none"])
    parser.add_argument("--kinds", nargs="+", default=["neural", "gaussian"])
    parser.add_argument("--iterations", type=int, default=2000)
    parser.add_argument("--jobs", type=int, default=2)
    a = parser.parse_args()
    jobs = []
    for spec in a.scene:
        name, _, rest = spec.partition("=")
        path, _, downscale = rest.partition(":")
        for budget in a.budgets:
            for kind in a.kinds:
                jobs.append((a.out, name, path, int(downscale or 1), kind, budget, a.iterations))
    with ThreadPoolExecutor(a.jobs) as pool:
        rows = list(pool.map(lambda job: run_one(*job), jobs))
    (a.out / "comparison.json").write_text(json.dumps(rows, indent=2))
    print("| scene | budget | kind | test PSNR | test SSIM | primitives | params | train s | train PSNR |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        if "error" in r:
            print(f"| {r['scene']} | {r['budget']} | {r['kind']} | failed: {r['error']} | | | | | |")
        else:
            print(f"| {r['scene']} | {r['budget']} | {r['kind']} | {r['psnr']:.2f} | {r['ssim']:.3f} | {r['primitives']} "
                  f"| {r['params']} | {r['train_seconds']:.0f} | {r['train_psnr']:.2f} |")


if __name__ == "__main__":
    main()
