"""Two installs of radfield, one benchmark, one run: the figures of the same `bench-*` command from
an old and a new version, run alternately (old, new, old, new, …) so that the machine's drift hits
both alike, with the median of each figure and the ratio new/old.

    python scripts/bench_versions.py OLD_RADFIELD NEW_RADFIELD --rounds 5 -- bench-render --primitives 10000

Each output line's decimal numbers are its figures; the rest of the line is its label, so any
bench-* command's table compares without knowing its layout. Used for the restructuring's
"figures within noise of before" check (docs/studies/restructuring.md)."""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
from collections import defaultdict

NUMBER = re.compile(r"(?<![\w.])-?\d+\.\d+(?![\w.])")


def figures(output: str) -> dict[str, list[float]]:
    rows = {}
    for line in output.splitlines():
        values = [float(x) for x in NUMBER.findall(line)]
        if values:
            rows[" ".join(NUMBER.sub("#", line).split())] = values
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("old"), parser.add_argument("new")
    parser.add_argument("--rounds", type=int, default=5)
    argv = sys.argv[1:]
    if "--" not in argv:
        parser.error("give the benchmark command after --")
    cut = argv.index("--")
    args, command = parser.parse_args(argv[:cut]), argv[cut + 1:]
    runs = {"old": defaultdict(list), "new": defaultdict(list)}
    for _ in range(args.rounds):
        for version in ("old", "new"):
            done = subprocess.run([getattr(args, version), *command], capture_output=True, text=True, check=True)
            for label, values in figures(done.stdout).items():
                runs[version][label].append(values)
    print(f"{' '.join(command)}: median of {args.rounds} alternating runs; ratio = new / old")
    for label, old_rows in runs["old"].items():
        new_rows = runs["new"].get(label)
        if not new_rows or len(new_rows[0]) != len(old_rows[0]):
            print(f"  only in the old version's output: {label}")
            continue
        old = [statistics.median(v) for v in zip(*old_rows)]
        new = [statistics.median(v) for v in zip(*new_rows)]
        cells = "  ".join(f"{o:g}->{n:g} ({n / o:.2f}x)" if o else f"{o:g}->{n:g}" for o, n in zip(old, new))
        print(f"  {label[:60]:60s} {cells}")


if __name__ == "__main__":
    main()
