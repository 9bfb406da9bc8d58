"""Mean ± standard deviation over seeds: for every group of finished runs STUDY/runs/<group>_s<seed>
(a seed set with `--seed N`), val PSNR (eval stage with eval.split=val), held-out PSNR (the train
log's last test_psnr), train PSNR and primitives, with the number of seeds. Only groups whose name
starts with PREFIX when one is given. Differences below about two standard deviations are noise.
    usage: STUDY=/work/q .venv/bin/python scripts/study/seeds.py [PREFIX] > seeds.md"""
import os
import re
import statistics
import sys
from collections import defaultdict
from pathlib import Path

from collect import run_figures


def mean_std(values: list[float], digits: int = 2) -> str:
    if len(values) < 2:
        return f"{values[0]:.{digits}f}"
    return f"{statistics.mean(values):.{digits}f} ± {statistics.stdev(values):.{digits}f}"


def main() -> None:
    study = Path(os.environ.get("STUDY", "/work/q")) / "runs"
    prefix = sys.argv[1] if len(sys.argv) > 1 else ""
    groups = defaultdict(list)
    for run in sorted(study.iterdir()):
        match = re.fullmatch(r"(.+)_s(\d+)", run.name)
        if match and match[1].startswith(prefix) and (figures := run_figures(run)) is not None:
            groups[match[1]].append(figures)
    print("| runs | seeds | val PSNR | held-out PSNR | train PSNR | primitives |")
    print("|---|---|---|---|---|---|")
    for name, runs in groups.items():
        val = [r["metrics"]["psnr"] for r in runs if r["metrics"].get("split") == "val"]
        print(f"| {name} | {len(runs)} | {mean_std(val) if val else '–'} | {mean_std([r['test'] for r in runs])} | "
              f"{mean_std([r['train_psnr'] for r in runs])} | "
              f"{mean_std([float(r['metrics']['num_primitives']) for r in runs], 0)} |")


if __name__ == "__main__":
    main()
