"""The progress bar every long piece of work shows (rich): description, bar, done/total, time left.
Disabled with quiet=True (`--quiet`, CI); transient, so finished bars leave the terminal clean."""

from __future__ import annotations


def progress_bar(quiet: bool):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                    disable=quiet, transient=True)
