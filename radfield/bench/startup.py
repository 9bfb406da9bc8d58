"""`radfield bench-startup`: how long the command line takes to start, against TARGET_SECONDS.

Each figure is the wall time of a fresh `python -m radfield [COMMAND] --help` process (interpreter
start-up included, as a user pays it), the median of `repeats` runs. A command module imports
torch, numpy and the geometry libraries inside the function that does its work, so that asking
for help costs only Typer's own start-up; tests/test_imports.py checks the imports themselves
(a timing on a shared machine is a figure, not a test).
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence

TARGET_SECONDS = 0.5


def startup_seconds(args: Sequence[str], repeats: int) -> float:
    """Median wall time of `repeats` fresh `python -m radfield ARGS` processes (each must succeed)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "radfield", *args], check=True, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL, env={**os.environ, "COLUMNS": "100"})
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def run_bench_startup(commands: Sequence[str], repeats: int = 5, echo: Callable[[str], None] = print) -> dict[str, float]:
    """Print the start-up time of `radfield --help` and of `radfield COMMAND --help` for each of
    `commands`, and how many exceed TARGET_SECONDS; returns {invocation: seconds}."""
    echo(f"bench-startup: median of {repeats} fresh processes each, target {TARGET_SECONDS:.1f} s")
    figures = {}
    for args in [["--help"]] + [[command, "--help"] for command in commands]:
        invocation = "radfield " + " ".join(args)
        seconds = figures[invocation] = startup_seconds(args, repeats)
        verdict = "ok" if seconds <= TARGET_SECONDS else "over the target"
        echo(f"  {invocation:36s} {seconds:6.3f} s  {verdict}")
    over = [name for name, seconds in figures.items() if seconds > TARGET_SECONDS]
    echo(f"  {len(figures) - len(over)} of {len(figures)} within {TARGET_SECONDS:.1f} s"
         + (f"; slowest {max(figures.values()):.3f} s" if figures else ""))
    return figures
