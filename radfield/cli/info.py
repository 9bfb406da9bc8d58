"""`radfield info`: what a run directory holds (radfield.pipeline.info)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def info(
    run_dir: Annotated[Path, typer.Argument(metavar="RUN", help="A run directory.")],
    as_json: Annotated[bool, typer.Option("--json", help="Machine-readable JSON (a stable interface).")] = False,
):
    """Stages done, their timings and key figures, the model, and the artifacts each stage wrote."""
    import json

    from radfield.pipeline.info import format_info, run_info

    summary = run_info(run_dir)
    typer.echo(json.dumps(summary, indent=2) if as_json else format_info(summary).rstrip())
