"""The `radfield` command line (Typer). Only argument handling lives here; the work is in
radfield.core, radfield.stages and radfield.datasets. A RadfieldError becomes one line on stderr
and exit code 1; anything else is a bug and keeps its traceback."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

import radfield
from radfield.cli import bench_train as bench_train_cli
from radfield.cli.common import parse_background, progress_bar, resolve_device, resolve_model
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


@app.command()
def reconstruct(
    input_path: Annotated[Path, typer.Argument(metavar="INPUT", help="Dataset folder (NeRF-synthetic, nerfstudio/instant-ngp, COLMAP) or a folder of photos (posed by SfM).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Run directory (created). Run again on it to resume or to redo only what changed.")],
    primitive: Annotated[Optional[str], typer.Option(help="neural (splattable neural primitives) or gaussian (3DGS baseline). (config key train.primitive)")] = None,
    max_primitives: Annotated[Optional[int], typer.Option(help="Hard primitive budget, initialised exactly (the paper's memory-budget protocol). (config key train.max_primitives)")] = None,
    iterations: Annotated[Optional[int], typer.Option(help="Optimisation steps. (config key train.iterations)")] = None,
    downscale: Annotated[Optional[int], typer.Option(help="Integer image downscale factor. (config key data.downscale)")] = None,
    background: Annotated[Optional[str], typer.Option(help="Background colour R,G,B in [0, 1] for RGBA images and renders. (config key data.background)")] = None,
    seed: Annotated[Optional[int], typer.Option(help="Random seed. (config key seed)")] = None,
    device: Annotated[Optional[str], typer.Option(help="cpu or cuda[:N]; not part of the cache key. (config key device)")] = None,
    config: Annotated[Optional[Path], typer.Option("--config", help="YAML file overriding pipeline.yaml (a partial copy).")] = None,
    sets: Annotated[Optional[list[str]], typer.Option("--set", metavar="KEY=VALUE", help="Override one config key, e.g. --set train.iterations=500 (repeatable; wins over the flags).")] = None,
    force: Annotated[Optional[list[str]], typer.Option("--force", metavar="STAGE", help="Re-run this stage even if cached (repeatable).")] = None,
    from_stage: Annotated[Optional[str], typer.Option("--from", metavar="STAGE", help="Re-run this stage and every later one.")] = None,
    until_stage: Annotated[Optional[str], typer.Option("--until", metavar="STAGE", help="Stop after this stage.")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress output (for CI); the summary is still printed.")] = False,
):
    """Reconstruct a radiance field from a dataset and print its held-out PSNR.

    Runs the cached stages sfm → data → envelope → tetra → init → train → eval in the run
    directory (sfm only for a folder of photos); a stage re-runs only when its inputs or its config
    keys changed."""
    from radfield.stages import registry
    from radfield.stages.config import load_config
    from radfield.stages.info import run_info
    from radfield.stages.pipeline import run_pipeline

    flags = {"train.primitive": primitive, "train.max_primitives": max_primitives, "train.iterations": iterations,
             "data.downscale": downscale, "seed": seed, "device": device,
             "data.background": list(parse_background(background)) if background is not None else None}
    cfg = load_config(config, sets or [], {key: value for key, value in flags.items() if value is not None})
    resolve_device(cfg["device"])
    registry.check(cfg, input_path)
    status = run_pipeline(registry.stages(), output, cfg, input_path=input_path, force=force or [],
                          from_stage=from_stage, until_stage=until_stage, quiet=quiet,
                          log=lambda line: typer.echo(line, err=True))
    typer.echo("stages: " + ", ".join(f"{name} {outcome}" for name, outcome in status.items()))
    info = run_info(output)
    evaluation = info["stages"].get("eval", {})
    if status.get("eval") in ("ran", "cached") and "psnr" in evaluation:
        split = cfg["eval"]["split"]
        what = "held-out" if split != "train" else "training-view"
        typer.echo(f"{what} PSNR {evaluation['psnr']:.2f} dB, SSIM {evaluation['ssim']:.4f} "
                   f"({evaluation['views']} {split} views); report {output / 'eval'}")
    if info["model"]:
        typer.echo(f"model: {info['model']}")


@app.command("eval")
def eval_command(
    target: Annotated[Path, typer.Argument(metavar="RUN_OR_MODEL", help="A run directory (its final model) or a .safetensors model file.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Report folder (created): metrics.json and renders/.")],
    dataset: Annotated[Optional[Path], typer.Option("--dataset", "-d", help="Dataset with the ground truth (default: the run's input; its SfM output for photos).")] = None,
    split: Annotated[str, typer.Option(help="train, val or test.")] = "test",
    downscale: Annotated[Optional[int], typer.Option(help="Image downscale factor (default: the run's, else 1).")] = None,
    background: Annotated[Optional[str], typer.Option(help="Background R,G,B (default: the run's, else 1,1,1).")] = None,
    device: Annotated[str, typer.Option(help="cpu or cuda.")] = "cpu",
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
):
    """Measure a trained model on a dataset split: PSNR, SSIM, FPS.

    Writes OUTPUT/metrics.json (per view and mean) and the renders to OUTPUT/renders/."""
    from radfield.stages.evaluate import eval_report

    options = {"data.downscale": downscale,
               "data.background": list(parse_background(background)) if background is not None else None}
    metrics = eval_report(target, dataset, split, output, options={k: v for k, v in options.items() if v is not None},
                          device=str(resolve_device(device)), quiet=quiet)
    typer.echo(f"{metrics['split']}: PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}, "
               f"{metrics['fps']:.1f} fps over {metrics['views']} views ({metrics['num_primitives']} "
               f"{metrics['kind']} primitives); report in {output}")


@app.command()
def info(
    run_dir: Annotated[Path, typer.Argument(metavar="RUN", help="A run directory.")],
    as_json: Annotated[bool, typer.Option("--json", help="Machine-readable JSON (a stable interface).")] = False,
):
    """Stages done, their timings and key figures, and the main artifacts of a run."""
    import json

    from radfield.stages.info import format_info, run_info

    summary = run_info(run_dir)
    typer.echo(json.dumps(summary, indent=2) if as_json else format_info(summary).rstrip())


@app.command()
def render(
    model_or_run: Annotated[Path, typer.Argument(help="A .safetensors model file, or a run directory (its final model).")],
    dataset: Annotated[Path, typer.Option("--dataset", "-d", help="Dataset whose cameras to render (NeRF-synthetic, nerfstudio or COLMAP).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder for the PNG frames (created).")],
    split: Annotated[str, typer.Option(help="Which cameras: train, val, test or all.")] = "test",
    background: Annotated[str, typer.Option(help="Background colour R,G,B in [0, 1].")] = "1,1,1",
    downscale: Annotated[int, typer.Option(help="Render at 1/K of the dataset's resolution.")] = 1,
    device: Annotated[str, typer.Option(help="cpu or cuda.")] = "cpu",
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
    with progress_bar(quiet) as progress:
        task = progress.add_task(f"rendering {len(cameras)} views", total=len(cameras))
        for view, cam in zip(data.views, cameras):
            start = time.perf_counter()
            with torch.no_grad():
                out = render_view(model, cam, background=bg)
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
    profile: Annotated[bool, typer.Option(help="Also print the torch profiler's top costs.")] = False,
):
    """Benchmark (not a test): forward and forward+backward time of neural primitives and 3D
    Gaussians on the same cameras and budgets; prints ms/frame, pairs/s and the time ratio."""
    from radfield.bench import run_bench

    if min(primitives, width, height, views, repeats) < 1:
        raise RadfieldError("--primitives, --width, --height, --views and --repeats must be positive")
    run_bench(primitives, width, height, views, repeats, str(resolve_device(device)), profile, echo=typer.echo)


app.command("bench-train")(bench_train_cli.bench_train)


@app.command("demo-scene")
def demo_scene(
    name: Annotated[str, typer.Argument(help="blobs (easy), thin (sub-pixel rods) or checker (high-frequency texture).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder to create (must not exist or be empty).")],
    train_views: Annotated[int, typer.Option(help="Training views.")] = 40,
    test_views: Annotated[int, typer.Option(help="Held-out test views.")] = 8,
    size: Annotated[int, typer.Option(help="Image width and height in pixels.")] = 64,
    seed: Annotated[int, typer.Option(help="Turns the camera spiral.")] = 0,
    exist_ok: Annotated[bool, typer.Option("--exist-ok", help="Do nothing if OUTPUT already holds this scene (same name and seed).")] = False,
):
    """Write a tiny synthetic NeRF-synthetic scene with exact ground truth (and its mesh.ply)."""
    import json

    from radfield.datasets.synthetic import generate_scene

    if exist_ok and (output / "scene.json").is_file():
        existing = json.loads((output / "scene.json").read_text())
        if existing.get("name") == name and existing.get("seed") == seed:
            typer.echo(f"{output} already holds the {name} scene")
            return
    generate_scene(name, output, n_train=train_views, n_test=test_views, size=size, seed=seed)
    typer.echo(f"wrote {name}: {train_views} train + {test_views} test views of {size}x{size} to {output}")


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
