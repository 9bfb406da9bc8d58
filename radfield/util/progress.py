"""The progress every long piece of work shows, on stderr (stdout carries only results):

- on a terminal, a rich bar: description, bar, done/total, elapsed and time left; transient, so
  finished bars leave the terminal clean;
- when stderr is a file or a pipe (a log, CI), a plain line every LINE_EVERY of the way instead
  ("evaluating 8 test views: 50% (4/8), 0:00:03 elapsed, 0:00:03 left"), never a blank line or
  a cursor movement;
- nothing with quiet=True (`--quiet`).

The object returned is used as rich's Progress is: `with progress_bar(quiet) as progress:`,
`task = progress.add_task(description, total=N)`, `progress.advance(task)`,
`progress.update(task, total=, completed=, description=, stats=)`. `stats=True` adds a column of
free text (the task's `stats` field: the training loss and PSNR).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field

LINE_EVERY = 0.1   # a plain line each time another tenth of the work is done


def progress_bar(quiet: bool, *, stats: bool = False):
    """A progress display for `with` (module docstring)."""
    if quiet:
        return _Silent()
    if sys.stderr.isatty():
        return _rich_bar(stats)
    return LineProgress(sys.stderr)


def _rich_bar(stats: bool):
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    columns = [TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn()]
    if stats:
        columns.append(TextColumn("{task.fields[stats]}"))
    return Progress(*columns, _times_column(), console=Console(stderr=True), transient=True)


def _times_column():
    """rich's column "0:00:03 elapsed, 0:00:05 left", worded as the plain lines are (rich's bare
    columns with a "left" between them read "0:00:03 left 0:00:05": the elapsed time looked like the
    time left); the time left, rich's estimate from the recent rate, only where the task has a total
    and is not done."""
    from rich.progress import ProgressColumn, TimeElapsedColumn, TimeRemainingColumn
    from rich.text import Text

    class Times(ProgressColumn):
        elapsed, left = TimeElapsedColumn(), TimeRemainingColumn()

        def render(self, task) -> Text:
            text = Text.assemble(self.elapsed.render(task), " elapsed")
            if task.total is not None and not task.finished:
                text.append_text(Text.assemble(", ", self.left.render(task), " left"))
            return text

    return Times()


class _Silent:
    """quiet: the same calls, nothing shown."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None

    def add_task(self, description: str, total: float | None = None, completed: float = 0, **fields) -> int:
        return 0

    def update(self, task: int, **changes) -> None:
        return None

    def advance(self, task: int, advance: float = 1) -> None:
        return None


@dataclass
class _Task:
    description: str
    total: float | None
    completed: float
    fields: dict
    start: float = field(default_factory=time.monotonic)
    shown: int = 0        # tenths already reported
    begun: float = 0.0    # completed when it was added (a resumed run's steps): not timed here

    def __post_init__(self):
        self.begun = self.completed
        self.shown = int(self.completed / self.total / LINE_EVERY + 1e-9) if self.total else 0


class LineProgress(_Silent):
    """Progress as plain lines on `stream`: one each time a task passes another LINE_EVERY of its
    total (so at most eleven a task, whatever its length), the last at 100%."""

    def __init__(self, stream):
        self.stream = stream
        self.tasks: list[_Task] = []

    def add_task(self, description: str, total: float | None = None, completed: float = 0, **fields) -> int:
        self.tasks.append(_Task(description, total, completed, fields))
        return len(self.tasks) - 1

    def update(self, task: int, *, total: float | None = None, completed: float | None = None,
               description: str | None = None, advance: float | None = None, **fields) -> None:
        t = self.tasks[task]
        t.description = description if description is not None else t.description
        t.total = total if total is not None else t.total
        t.completed = completed if completed is not None else t.completed + (advance or 0)
        t.fields.update(fields)
        self._report(t)

    def advance(self, task: int, advance: float = 1) -> None:
        self.update(task, advance=advance)

    def _report(self, t: _Task) -> None:
        if not t.total:
            return
        done = min(t.completed / t.total, 1.0)
        tenths = int(done / LINE_EVERY + 1e-9)
        if tenths <= t.shown:
            return
        t.shown = tenths
        elapsed = time.monotonic() - t.start
        rate = (t.completed - t.begun) / max(elapsed, 1e-9)
        left = f", {_clock((t.total - t.completed) / rate)} left" if done < 1 and rate > 0 else ""
        stats = f", {t.fields['stats']}" if t.fields.get("stats") else ""
        print(f"{t.description}: {done:.0%} ({t.completed:g}/{t.total:g}){stats}, {_clock(elapsed)} elapsed{left}",
              file=self.stream, flush=True)


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"
