"""`radfield bench-quality DATASET`: the paper's memory-budget protocol. Neural primitives against
3D Gaussians, each at several hard primitive budgets (`train.max_primitives`) and unbudgeted
(densification without a cap), on one dataset, as a table and a plot of held-out PSNR against the
parameter count.

Every (kind, budget) is a `radfield reconstruct` in OUT/runs/<kind>-<budget>/ (a cached run: asking
again reuses finished runs and resumes killed ones), run as a subprocess with OMP_NUM_THREADS=1, `jobs`
at a time (two busy OpenMP pools on two cores slow each other down badly). A budgeted run starts from
exactly `budget` primitives and does not densify (the paper's protocol; train.max_primitives, see
core/train/strategy.py); an unbudgeted one densifies without a cap. The densification schedule
(train.densify.start, .stop and the Gaussians' .gaussian.opacity_reset_every) is the defaults'
(pipeline.yaml) scaled by iterations / train.iterations, so at the default iteration count every
unbudgeted run is a default run and shorter benchmarks still densify and reset inside their window.

OUT/bench.json   [{"kind" (the kind that trained: --kinds' neural is neural-relight on a one-light-at-a-time
                   dataset, neural-dynamic on a dynamic one; stages/init.primitive_kind), "budget" (int or null),
                   "run", "psnr", "ssim", "lpips", "primitives",
                   "params", "size_bytes", "fps", "train_seconds", "train_psnr", "stage_seconds"
                   ({stage: seconds} of the run's stages), "pipeline_seconds" (their sum), "wall_seconds"
                   (of the reconstruct process this time, start-up included; small for a cached run)}
                  or {"kind", "budget", "run", "error"}]
OUT/bench.md     the table
OUT/psnr_vs_params.png   PSNR (dB) against parameters (log scale), one line per kind
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Sequence

from radfield.util.atomic import atomic_write, atomic_write_text
from radfield.errors import RadfieldError
from radfield.evaluation.report import human_bytes

RUNS = "runs"
TABLE, RESULTS, PLOT = "bench.md", "bench.json", "psnr_vs_params.png"


def parse_budgets(text: str) -> list[int | None]:
    """"500,2000,none" -> [500, 2000, None]."""
    out: list[int | None] = []
    for item in (t.strip() for t in text.split(",")):
        if item.lower() in ("none", "unbudgeted", "inf"):
            out.append(None)
            continue
        try:
            value = int(item)
        except ValueError:
            value = 0
        if value < 1:
            raise RadfieldError(f"--budgets takes positive integers and 'none', comma-separated, got {item!r}")
        out.append(value)
    if not out or len(set(out)) != len(out):
        raise RadfieldError(f"--budgets must list distinct budgets, got {text!r}")
    return out


def run_name(kind: str, budget: int | None) -> str:
    return f"{kind}-{'none' if budget is None else budget}"


def default_iterations() -> int:
    from radfield.pipeline.config import load_defaults

    return int(load_defaults()["train"]["iterations"])


def schedule(iterations: int) -> dict[str, int]:
    """The defaults' densification schedule scaled from train.iterations to `iterations` steps
    (the defaults themselves at the default iteration count)."""
    from radfield.pipeline.config import load_defaults

    train = load_defaults()["train"]
    densify, scale = train["densify"], iterations / train["iterations"]
    return {"train.densify.start": round(densify["start"] * scale),
            "train.densify.stop": round(densify["stop"] * scale),
            "train.densify.gaussian.opacity_reset_every": max(round(densify["gaussian"]["opacity_reset_every"] * scale), 1)}


def reconstruct_args(dataset: Path, run: Path, kind: str, budget: int | None, iterations: int,
                     sets: Sequence[str]) -> list[str]:
    args = [sys.executable, "-m", "radfield", "reconstruct", str(dataset), "-o", str(run), "--primitive", kind,
            "--iterations", str(iterations), "--quiet"]
    for key, value in schedule(iterations).items():
        args += ["--set", f"{key}={value}"]
    if budget is not None:
        args += ["--max-primitives", str(budget)]
    for item in sets:
        args += ["--set", item]
    return args


def run_one(dataset: Path, out: Path, kind: str, budget: int | None, iterations: int, sets: Sequence[str]) -> dict[str, Any]:
    from radfield.pipeline.info import run_info
    from radfield.run import Run

    run = out / RUNS / run_name(kind, budget)
    row: dict[str, Any] = {"kind": kind, "budget": budget, "run": str(run)}
    start = time.perf_counter()
    proc = subprocess.run(reconstruct_args(dataset, run, kind, budget, iterations, sets), capture_output=True,
                          text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        lines = proc.stderr.strip().splitlines()
        return {**row, "error": lines[-1] if lines else f"exit code {proc.returncode}"}
    metrics = json.loads(Run(run).metrics.read_text())
    stages = run_info(run)["stages"]
    train = stages.get("train", {})
    seconds = {name: info["seconds"] for name, info in stages.items() if info.get("seconds") is not None}
    # the kind that trained: on a dynamic or relighting dataset the conditioned kind reconstruct chose
    return {**row, "kind": metrics["kind"], "psnr": metrics["psnr"], "ssim": metrics["ssim"], "lpips": metrics.get("lpips"),
            "primitives": metrics["num_primitives"], "params": metrics["num_params"],
            "size_bytes": metrics["file_size_bytes"], "fps": metrics["fps"], "train_seconds": train.get("seconds"),
            "train_psnr": train.get("train_psnr"), "stage_seconds": seconds,
            "pipeline_seconds": sum(seconds.values()), "wall_seconds": wall}


def bench_quality(dataset: Path, out: Path, *, budgets: Sequence[int | None], kinds: Sequence[str], iterations: int,
                  sets: Sequence[str] = (), jobs: int = 2, on_done: Callable[[dict], None] | None = None) -> list[dict]:
    """Run every (kind, budget) and write the table, the JSON and the plot into `out`."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise RadfieldError(f"{out}: exists and is not a folder")
    (out / RUNS).mkdir(parents=True, exist_ok=True)
    combos = [(kind, budget) for budget in budgets for kind in kinds]

    def job(combo):
        row = run_one(dataset, out, combo[0], combo[1], iterations, sets)
        if on_done is not None:
            on_done(row)
        return row

    with ThreadPoolExecutor(max(1, jobs)) as pool:
        rows = list(pool.map(job, combos))
    atomic_write_text(out / RESULTS, json.dumps(rows, indent=1) + "\n")
    atomic_write_text(out / TABLE, table(rows, dataset=dataset, iterations=iterations))
    if any("error" not in r for r in rows):
        atomic_write(out / PLOT, lambda tmp: plot(rows, tmp, title=f"{Path(dataset).name}, {iterations} iterations"))
    return rows


def table(rows: Sequence[dict], *, dataset: Path, iterations: int) -> str:
    lines = [f"# Quality at equal primitive budgets: {dataset} ({iterations} iterations)", "",
             "| budget | kind | PSNR (dB) | train PSNR | SSIM | LPIPS | primitives | parameters | size | FPS | train time "
             "| all stages |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        budget = "none" if r["budget"] is None else str(r["budget"])
        if "error" in r:
            lines.append(f"| {budget} | {r['kind']} | failed: {r['error']} | | | | | | | | | |")
            continue
        lp = "–" if r["lpips"] is None else f"{r['lpips']:.4f}"
        seconds = "–" if r["train_seconds"] is None else f"{r['train_seconds']:.0f} s"
        fit = "–" if r.get("train_psnr") is None else f"{r['train_psnr']:.2f}"
        total = "–" if r.get("pipeline_seconds") is None else f"{r['pipeline_seconds']:.0f} s"
        lines.append(f"| {budget} | {r['kind']} | {r['psnr']:.2f} | {fit} | {r['ssim']:.4f} | {lp} | {r['primitives']} | "
                     f"{r['params']} | {human_bytes(r['size_bytes'])} | {r['fps']:.2f} | {seconds} | {total} |")
    return "\n".join(lines) + "\n"


def plot(rows: Sequence[dict], path: Path, *, title: str) -> None:
    """PSNR against parameters, one line per kind through its budgets; unbudgeted runs hollow."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    for kind, colour in zip(sorted({r["kind"] for r in rows}), ("tab:blue", "tab:orange", "tab:green")):
        done = sorted((r for r in rows if r["kind"] == kind and "error" not in r), key=lambda r: r["params"])
        if not done:
            continue
        ax.plot([r["params"] for r in done], [r["psnr"] for r in done], "-", color=colour, label=kind)
        for r in done:
            unbudgeted = r["budget"] is None
            ax.plot(r["params"], r["psnr"], "o", color=colour, markerfacecolor="white" if unbudgeted else colour)
            ax.annotate("no cap" if unbudgeted else str(r["budget"]), (r["params"], r["psnr"]), fontsize=7,
                        xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("parameters")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, format="png")
    plt.close(fig)
