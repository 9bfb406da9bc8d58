"""Budget table of the study: neural against Gaussian per scene and primitive budget, from run
folders named by the queue (STUDY/runs/NAME). Held-out = the test split (train log's last
test_psnr); val where the run has a val split (eval.split=val), else –.
    usage: STUDY=/work/q .venv/bin/python scripts/study/budget_table.py [ROWS]
ROWS: a file of lines "scene | budget | neural run | Gaussian run" replacing the rows below; a run
given as an absolute path is read from there instead of STUDY/runs (e.g. Gaussian runs of an
earlier study that nothing since has changed, or the runs of `radfield bench-quality`:
OUT/runs/neural-500 …)."""
import json
import os
import sys
from pathlib import Path

study = Path(os.environ.get("STUDY", "/work/q")) / "runs"
ROWS = [("glossy (90 train / 10 val / 20 test, 64×64)", "500", "b_neural_500", "b_gauss_500"),
        ("glossy", "2000", "b_neural_2000", "b_gauss_2000"),
        ("glossy", "8000", "b_neural_8000", "b_gauss_8000"),
        ("glossy", "none", "g_om10", "g_gauss_reset1000"),
        ("lego_small (--downscale 8: 50×50; 90 / 10 / 25)", "none", "l_neural", "l_gauss"),
        ("fern (--downscale 8: 63×47; 17 train / 3 test, no val)", "none", "f_neural", "f_gauss"),
        ("fox_small photos (SfM, --downscale 4: 56×100; 39 / 4 / 7)", "none", "x_neural", "x_gauss")]

if len(sys.argv) > 1:
    ROWS = [tuple(x.strip() for x in line.split("|")) for line in Path(sys.argv[1]).read_text().splitlines()
            if line.strip() and not line.startswith("#")]


def figures(name):
    run = study / name  # an absolute name stays as it is
    try:
        metrics = json.loads((run / "eval" / "metrics.json").read_text())
        train = json.loads((run / "train" / "manifest.json").read_text())["figures"]
        log = [json.loads(x) for x in (run / "train" / "log.jsonl").read_text().splitlines()]
    except (OSError, ValueError, KeyError):
        return None
    test = [r["test_psnr"] for r in log if r.get("test_psnr") is not None][-1]
    val = f"{metrics['psnr']:.2f}" if metrics.get("split") == "val" else "–"
    return test, f"{test:.2f} | {val} | {train['train_psnr']:.2f} | {metrics['num_primitives']:,}"


print("| scene | budget | neural held-out | val | train | primitives | Gaussian held-out | val | train | primitives "
      "| held-out neural − Gaussian |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
for scene, budget, neural, gaussian in ROWS:
    a, b = figures(neural), figures(gaussian)
    difference = f"{a[0] - b[0]:+.2f}" if a and b else "–"
    print(f"| {scene} | {budget} | {a[1] if a else 'not run | | |'} | {b[1] if b else 'not run | | |'} | {difference} |")
