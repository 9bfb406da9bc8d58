"""Table of the capture study: for each run of the queue files (lines NAME FROM DATASET OPTIONS…,
scripts/study/run_capture.sh) its val PSNR (the eval stage, eval.split=val), held-out (test) PSNR
(the train log's last test_psnr), train PSNR, train − held-out, primitives and train seconds.
Selection is on val; test is only reported.
    usage: STUDY=/work/runs/capture .venv/bin/python scripts/study/collect_capture.py QUEUE... > table.md"""
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from collect import run_figures  # noqa: E402  (the study's reader of a finished run)

study = Path(os.environ.get("STUDY", "/work/runs/capture"))
SKIP = ("data.val_every", "eval.split")
print("| run | scene | options (besides the protocol) | val PSNR | held-out PSNR | train PSNR | train − held-out | primitives | train s |")
print("|---|---|---|---|---|---|---|---|---|")
for queue in sys.argv[1:]:
    for line in Path(queue).read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        name, _, dataset, *options = line.split()
        options = [o for o in options if o != "--set" and not o.startswith(SKIP)]
        scene = Path(dataset).name if Path(dataset).name != "images" else Path(dataset).parent.name
        if "--downscale" in options:
            k = options.index("--downscale")
            scene += f" /{options[k + 1]}"
            del options[k:k + 2]
        figures = run_figures(study / "runs" / name)
        if figures is None:
            continue
        metrics, test, train_psnr = figures["metrics"], figures["test"], figures["train_psnr"]
        val = f"{metrics['psnr']:.2f}" if metrics.get("split") == "val" else "–"
        print(f"| {name} | {scene} | {' '.join(options)} | {val} | {test:.2f} | {train_psnr:.2f} | "
              f"{train_psnr - test:.2f} | {metrics['num_primitives']} | {figures['seconds']:.0f} |")
