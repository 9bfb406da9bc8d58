"""One static model per timestep (issue 29's "obvious alternative" to a dynamic model): from a D-NeRF
dataset DATA (frames with "time", e.g. `radfield demo-scene smoke`), for each chosen moment make a
static NeRF-synthetic subset (that moment's train and test frames, "time" dropped, images linked),
reconstruct it with `--max-primitives BUDGET / moments` and `--iterations STEPS`, and print one
table row per moment (held-out PSNR/SSIM/LPIPS, primitives, model bytes, wall time) and the means.
With DYNAMIC_RUN given, its eval/metrics.json `per_time` rows are printed beside them, for the
same moments, with its own model bytes: the comparison the issue asks for.
    usage: OMP_NUM_THREADS=1 .venv/bin/python scripts/study/per_time_static.py DATA OUT \\
               [--budget 4000] [--steps 500] [--every 1] [--dynamic-run RUN] [--primitive neural]
`--every k` takes every k-th moment (a spread subset; the budget is still divided by all moments).
Runs that finished are reused (reconstruct's cache), so the script can be stopped and rerun."""
import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

RADFIELD = Path(sys.executable).parent / "radfield"


def moments_of(data: Path) -> list[float]:
    frames = json.loads((data / "transforms_train.json").read_text())["frames"]
    return sorted({frame["time"] for frame in frames})


def static_subset(data: Path, xi: float, out: Path) -> Path:
    """`out`: the frames of `data` at time ξ as a static NeRF-synthetic dataset (no "time" keys)."""
    out.mkdir(parents=True, exist_ok=True)
    for split in ("train", "test"):
        meta = json.loads((data / f"transforms_{split}.json").read_text())
        meta["frames"] = [{k: v for k, v in f.items() if k != "time"} for f in meta["frames"] if f["time"] == xi]
        (out / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))
        if not (out / split).exists():
            (out / split).symlink_to((data / split).resolve())  # the reader opens only the listed frames
    return out


def reconstruct(dataset: Path, run: Path, budget: int, steps: int, primitive: str) -> float:
    """Wall seconds of `radfield reconstruct` (those recorded in RUN/wall_s.txt when the run was already complete)."""
    if (run / "eval" / "metrics.json").is_file():
        return float((run / "wall_s.txt").read_text()) if (run / "wall_s.txt").is_file() else 0.0
    start = time.time()
    subprocess.run([str(RADFIELD), "reconstruct", str(dataset), "-o", str(run), "--primitive", primitive,
                    "--max-primitives", str(budget), "--iterations", str(steps), "-q"], check=True,
                   env={**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")},
                   stdout=subprocess.DEVNULL)
    (run / "wall_s.txt").write_text(f"{time.time() - start:.1f}")
    return time.time() - start


def fmt(x, digits: int = 3) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--budget", type=int, default=4000)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--primitive", default="neural")
    parser.add_argument("--dynamic-run", type=Path)
    args = parser.parse_args()
    moments = moments_of(args.data)
    per_model = args.budget // len(moments)
    dynamic = {}
    if args.dynamic_run:
        metrics = json.loads((args.dynamic_run / "eval" / "metrics.json").read_text())
        dynamic = {row["time"]: row for row in metrics["per_time"]}
        dynamic_bytes = metrics["file_size_bytes"]
    print(f"{len(moments[::args.every])} of {len(moments)} moments, {per_model} primitives each "
          f"(budget {args.budget}), {args.steps} steps, {args.primitive}")
    print("| ξ | static PSNR | SSIM | LPIPS | primitives | model bytes | wall s | dynamic PSNR at ξ |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    rows = []
    for k, xi in list(enumerate(moments))[::args.every]:
        subset = static_subset(args.data, xi, args.out / "data" / f"t{k:03d}")
        wall = reconstruct(subset, args.out / "runs" / f"t{k:03d}", per_model, args.steps, args.primitive)
        m = json.loads((args.out / "runs" / f"t{k:03d}" / "eval" / "metrics.json").read_text())
        d = dynamic.get(xi, {}).get("psnr")
        rows.append({"time": xi, "psnr": m["psnr"], "ssim": m["ssim"], "lpips": m.get("lpips"), "dynamic": d,
                     "primitives": m["num_primitives"], "bytes": m["file_size_bytes"], "wall": wall})
        print(f"| {xi:.3f} | {m['psnr']:.2f} | {m['ssim']:.4f} | {fmt(m.get('lpips'))} | {m['num_primitives']} | "
              f"{m['file_size_bytes']} | {wall:.0f} | {fmt(d, 2)} |", flush=True)
    mean = {key: statistics.mean(r[key] for r in rows) if all(r[key] is not None for r in rows) else None
            for key in ("psnr", "ssim", "lpips", "dynamic")}
    total_bytes = sum(r["bytes"] for r in rows) * len(moments) / len(rows)   # all moments' models
    print(f"\nmean over the {len(rows)} moments: static {fmt(mean['psnr'], 2)} dB, SSIM {fmt(mean['ssim'], 4)}, "
          f"LPIPS {fmt(mean['lpips'])}; dynamic at the same moments {fmt(mean['dynamic'], 2)} dB")
    print(f"model bytes: {len(moments)} static models {total_bytes:.0f} (extrapolated when --every > 1)"
          + (f", the dynamic model {dynamic_bytes}" if dynamic else ""))
    print(f"static wall time: {sum(r['wall'] for r in rows):.0f} s for {len(rows)} models")
    (args.out / "per_time_static.json").write_text(json.dumps({"rows": rows, "mean": mean}, indent=1))


if __name__ == "__main__":
    main()
