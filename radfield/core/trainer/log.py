"""The training log: one JSON object per optimiser step in a JSON-lines file, and its curves.

A record holds what the trainer reports after a step (radfield.core.trainer.loop.train's on_step):
step, loss, psnr (of that step's training views), primitives, seconds (wall time since training
began, summed over resumed attempts), what population control did (cloned, split, pruned, when
it ran) and test_psnr on the steps where held-out views were measured. The log is appended to
and flushed line by line as the trainer hands the records over (every step on the CPU; every
`train.log_every` steps on a GPU, where the trainer reads the device that rarely, and always at a
checkpoint's step), so a killed run keeps everything up to its last hand-over; resuming from a
checkpoint first drops the records after the checkpoint's step, so the log of a resumed run reads
as that of an uninterrupted one.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from radfield.util.atomic import atomic_write, atomic_write_text


def read_log(path: str | Path) -> list[dict[str, Any]]:
    """The records of a log file (none if it does not exist); a line cut short by a kill is skipped."""
    path = Path(path)
    if not path.is_file():
        return []
    records = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            record = json.loads(line)
        except ValueError:
            continue
        if isinstance(record, dict) and isinstance(record.get("step"), int):
            records.append(record)
    return records


class TrainLog:
    """An append-only log at `path` that starts with `records` (atomically rewritten first)."""

    def __init__(self, path: str | Path, records: list[dict[str, Any]] = ()):
        self.path = Path(path)
        self.records = list(records)
        atomic_write_text(self.path, "".join(_line(r) for r in self.records))
        self._file = open(self.path, "a", encoding="utf-8")

    @property
    def seconds(self) -> float:
        """The training time the log already accounts for."""
        return self.records[-1].get("seconds", 0.0) if self.records else 0.0

    def write(self, record: dict[str, Any]) -> None:
        self.records.append(record)
        self._file.write(_line(record))
        self._file.flush()

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> "TrainLog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _line(record: dict[str, Any]) -> str:
    # NaN/inf are not JSON: a diverged loss is logged as null
    clean = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in record.items()}
    return json.dumps(clean, sort_keys=True) + "\n"


def plot_curves(records: list[dict[str, Any]], path: str | Path, title: str = "training") -> None:
    """Write a PNG (matplotlib, Agg backend): loss (log scale), train and held-out PSNR, and the
    primitive count over the steps of `records`."""
    import matplotlib

    matplotlib.use("Agg")  # no display; must precede pyplot
    from matplotlib.figure import Figure

    steps = [r["step"] for r in records]
    figure = Figure(figsize=(12, 3.6), layout="constrained")
    loss_ax, psnr_ax, count_ax = figure.subplots(1, 3)
    loss_ax.plot(steps, [_value(r, "loss") for r in records], lw=0.8)
    if any((_value(r, "loss") or 0) > 0 for r in records):
        loss_ax.set_yscale("log")
    loss_ax.set(title="loss", xlabel="step")
    psnr_ax.plot(steps, [_value(r, "psnr") for r in records], lw=0.6, alpha=0.7, label="train views (per step)")
    held = [(r["step"], r["test_psnr"]) for r in records if r.get("test_psnr") is not None]
    if held:
        psnr_ax.plot(*zip(*held), "o-", ms=3, label="held-out views")
    psnr_ax.set(title="PSNR (dB)", xlabel="step")
    psnr_ax.legend(loc="lower right", fontsize="small")
    count_ax.plot(steps, [r.get("primitives") for r in records], lw=1.0)
    count_ax.set(title="primitives", xlabel="step")
    figure.suptitle(title)
    atomic_write(path, lambda tmp: figure.savefig(tmp, format="png", dpi=100))


def _value(record: dict[str, Any], key: str) -> float:
    value = record.get(key)
    return math.nan if value is None else value
