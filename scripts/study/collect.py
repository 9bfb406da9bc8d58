"""Table of the quality study: for each run NAME in the queue files given, its held-out (test) PSNR
(the train log's last test_psnr), val PSNR (the eval stage, run with eval.split=val), train PSNR
(train stage), the train-test gap, primitives and train seconds. Selection is on val; test is
only reported.   usage: STUDY=/work/q .venv/bin/python scripts/study/collect.py QUEUE... > table.md"""
import json
import os
import sys
from pathlib import Path



def run_figures(run: Path) -> dict | None:
    """A finished run's eval metrics, last held-out PSNR, train PSNR and train seconds (None: unfinished)."""
    try:
        metrics = json.loads((run / "eval" / "metrics.json").read_text())
        log = [json.loads(x) for x in (run / "train" / "log.jsonl").read_text().splitlines()]
        train = json.loads((run / "train" / "manifest.json").read_text())
    except (OSError, ValueError):
        return None
    test = [r["test_psnr"] for r in log if r.get("test_psnr") is not None][-1]
    info = (train or {}).get("figures", train or {})
    return {"metrics": metrics, "test": test, "train_psnr": info.get("train_psnr"), "seconds": log[-1]["seconds"]}


def main() -> None:
    study = Path(os.environ.get("STUDY", "/work/q"))
    print("| run | options (besides the study protocol) | ω0 | val PSNR | held-out PSNR | train PSNR | train − held-out | primitives | train s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for queue in sys.argv[1:]:
        for line in Path(queue).read_text().splitlines():
            if not line.strip() or line.startswith("#"):
                continue
            name, _, *options = line.split()
            options = " ".join(o for o in options if o != "--set" and not o.startswith(("data.val_every", "eval.split",
                                                                                        "render.omega0")))
            run = study / "runs" / name
            figures = run_figures(run)
            if figures is None:
                continue
            metrics, test, train_psnr = figures["metrics"], figures["test"], figures["train_psnr"]
            config = (run / "config.yaml").read_text()
            omega0 = config.split("omega0: ")[1].split(",")[0].split()[0] if "gaussian" not in options else "–"
            val = metrics["psnr"] if metrics.get("split") == "val" else float("nan")
            print(f"| {name} | {options} | {omega0} | {val:.2f} | {test:.2f} | {train_psnr:.2f} | {train_psnr - test:.2f} | "
                  f"{metrics['num_primitives']} | {figures['seconds']:.0f} |")


if __name__ == "__main__":
    main()
