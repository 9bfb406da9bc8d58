"""Where the time of a `radfield reconstruct` goes: each stage's seconds (its manifest), and the train
stage split by its log (RUN/train/log.jsonl, `seconds` since the stage started, per step): set-up
before the first step, the steps themselves, the held-out evaluations every train.eval_every steps
and the checkpoints (the extra time of the steps that log a test_psnr, over the median step; both
every 500 steps by default), and the tail after the
last step (the train PSNR over the training views, writing the model).
    usage: .venv/bin/python scripts/study/stage_profile.py RUN [WALL_SECONDS]   (markdown table)"""
import json
import statistics
import sys
from pathlib import Path

from radfield.pipeline.info import run_info

run = Path(sys.argv[1])
wall = float(sys.argv[2]) if len(sys.argv) > 2 else None
stages = {name: info["seconds"] for name, info in run_info(run)["stages"].items() if info.get("seconds")}
log = [json.loads(line) for line in (run / "train" / "log.jsonl").read_text().splitlines()]
steps = [r for r in log if "step" in r]
dt = [b["seconds"] - a["seconds"] for a, b in zip(steps, steps[1:])]
median = statistics.median(dt)
evals = sum(d - median for d, r in zip(dt, steps[1:]) if r.get("test_psnr") is not None)
setup = steps[0]["seconds"] - median
tail = stages["train"] - steps[-1]["seconds"]
loop = steps[-1]["seconds"] - steps[0]["seconds"] + median - evals
total = sum(stages.values())
print(f"| part | seconds | share of {'the wall time' if wall else 'all stages'} |")
print("|---|---|---|")
base = wall or total
for name, seconds in stages.items():
    print(f"| {name} | {seconds:.1f} | {seconds / base:.1%} |")
    if name == "train":
        for part, s in (("train: set-up", setup), (f"train: {len(steps)} steps ({median * 1e3:.1f} ms median)", loop),
                        ("train: held-out evaluations and checkpoints", evals), ("train: tail (train PSNR, writing)", tail)):
            print(f"| {part} | {s:.1f} | {s / base:.1%} |")
print(f"| all stages | {total:.1f} | {total / base:.1%} |")
if wall:
    print(f"| process start-up, config, cache checks | {wall - total:.1f} | {(wall - total) / wall:.1%} |")
    print(f"| `radfield reconstruct` wall time | {wall:.1f} | 100% |")
