"""The `radfield` command line (Typer). Only argument handling lives here; the work is in
radfield.core, radfield.stages and radfield.datasets. A RadfieldError becomes one line on stderr
and exit code 1; anything else is a bug and keeps its traceback."""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

import radfield
from radfield.core.errors import RadfieldError

app = typer.Typer(
    name="radfield",
    help="Reconstruct, edit, render and evaluate radiance fields made of splattable neural primitives.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(value: bool):
    if value:
        typer.echo(f"radfield {radfield.__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                                help="Print the version and exit.")] = False):
    """radfield: editable radiance fields from multi-view images."""


def parse_background(text: str) -> tuple[float, float, float]:
    """'R,G,B' with components in [0, 1] (e.g. 1,1,1 for white)."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in values):
        raise RadfieldError(f"--background must be three numbers in [0, 1] like 1,1,1, got {text!r}")
    return values


def resolve_device(name: str):
    import torch

    if name not in ("cpu", "cuda") and not name.startswith("cuda:"):
        raise RadfieldError(f"--device must be cpu or cuda[:N], got {name!r}")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise RadfieldError(f"--device {name}: this torch build sees no CUDA device (use --device cpu)")
    return torch.device(name)


def resolve_model(path: Path) -> Path:
    """A model file, or a run directory whose final model is used."""
    from radfield.stages.info import model_path

    if path.is_dir():
        model = model_path(path)
        if not model.is_file():
            raise RadfieldError(f"{path}: run directory has no trained model yet ({model} is missing)")
        return model
    if not path.exists():
        raise RadfieldError(f"{path}: no such model file or run directory")
    return path


@app.command()
def render(
    model_or_run: Annotated[Path, typer.Argument(help="A .safetensors model file, or a run directory (its final model).")],
    dataset: Annotated[Path, typer.Option("--dataset", "-d", help="Dataset whose cameras to render (NeRF-synthetic, nerfstudio or COLMAP).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder for the PNG frames (created).")],
    split: Annotated[str, typer.Option(help="Which cameras: train, val, test or all.")] = "test",
    background: Annotated[str, typer.Option(help="Background colour R,G,B in [0, 1].")] = "1,1,1",
    downscale: Annotated[int, typer.Option(help="Render at 1/K of the dataset's resolution.")] = 1,
    device: Annotated[str, typer.Option(help="cpu or cuda.")] = "cpu",
    compiled: Annotated[bool, typer.Option("--compiled/--eager", help="torch.compile the pair kernels (faster after a ~1 min first compile, cached on disk).")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
):
    """Render every camera of a dataset split to OUTPUT/<frame name>.png."""
    import torch

    from radfield.core.io import load_model
    from radfield.core.rasterize import render as render_view
    from radfield.datasets.images import write_image
    from radfield.datasets.readers import load_dataset

    bg = parse_background(background)
    dev = resolve_device(device)
    model = load_model(resolve_model(model_or_run), device=dev)
    data = load_dataset(dataset, split=split, downscale=downscale, background=bg)
    cameras = data.cameras
    if output.exists() and not output.is_dir():
        raise RadfieldError(f"{output}: exists and is not a folder")
    output.mkdir(parents=True, exist_ok=True)
    seconds = []
    with _progress(quiet) as progress:
        task = progress.add_task(f"rendering {len(cameras)} views", total=len(cameras))
        for view, cam in zip(data.views, cameras):
            start = time.perf_counter()
            with torch.no_grad():
                out = render_view(model, cam, background=bg, compiled=compiled)
            seconds.append(time.perf_counter() - start)
            write_image(output / f"{view.image_path.stem}.png", out.color.clamp(0, 1).cpu().numpy())
            progress.advance(task)
    typer.echo(f"rendered {len(cameras)} views ({cameras[0].width}x{cameras[0].height}, {len(model)} {model.kind} primitives) "
               f"to {output}; mean render time {1e3 * sum(seconds) / len(seconds):.1f} ms/frame")


@app.command("bench-render")
def bench_render(
    primitives: Annotated[int, typer.Option(help="Number of primitives.")] = 10_000,
    width: Annotated[int, typer.Option(help="Image width.")] = 256,
    height: Annotated[int, typer.Option(help="Image height.")] = 256,
    views: Annotated[int, typer.Option(help="Cameras on an orbit.")] = 4,
    repeats: Annotated[int, typer.Option(help="Timed passes over the cameras.")] = 2,
    device: Annotated[str, typer.Option(help="cpu or cuda.")] = "cpu",
    compiled: Annotated[bool, typer.Option("--compiled/--eager", help="torch.compile the pair kernels (compile time excluded).")] = False,
    profile: Annotated[bool, typer.Option(help="Also print the torch profiler's top costs.")] = False,
):
    """Benchmark (not a test): forward and forward+backward time of neural primitives and 3D
    Gaussians on the same cameras and budgets; prints ms/frame, pairs/s and the time ratio."""
    from radfield.bench import run_bench

    if min(primitives, width, height, views, repeats) < 1:
        raise RadfieldError("--primitives, --width, --height, --views and --repeats must be positive")
    run_bench(primitives, width, height, views, repeats, str(resolve_device(device)), compiled, profile, echo=typer.echo)


def _progress(quiet: bool):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                    disable=quiet, transient=True)


def main() -> None:
    try:
        app()
    except RadfieldError as e:
        typer.echo(f"radfield: error: {e}", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        typer.echo("radfield: interrupted", err=True)
        sys.exit(130)


if __name__ == "__main__":
    main()
