"""The `radfield` command line (Typer). Only argument handling lives here; the work is in
radfield.core, radfield.stages and radfield.datasets. A RadfieldError becomes one line on stderr
and exit code 1; anything else is a bug and keeps its traceback."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

import radfield
from radfield.cli import animate as animate_cli
from radfield.cli import edit as edit_cli
from radfield.cli import evaluate as evaluate_cli
from radfield.cli import export as export_cli, view as view_cli
from radfield.cli import bench_dist as bench_dist_cli
from radfield.cli import bench_train as bench_train_cli
from radfield.cli import distributed as distributed_cli
from radfield.cli.common import parse_background, progress_bar, resolve_device, resolve_model
from radfield.errors import RadfieldError

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
    iterations: Annotated[Optional[int], typer.Option(help="Optimisation steps; raising it on a finished run continues from its final state (see README). (config key train.iterations)")] = None,
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
    no_cage: Annotated[bool, typer.Option("--no-cage", help="Build no envelope and no editing cage (init and train run as for a dataset without geometry). (config key envelope.source=none)")] = False,
    nproc: Annotated[int, typer.Option("--nproc", min=1, help="Train data-parallel on this many local ranks, started here through torch's launcher (train.batch_views is split across them; README 'Distributed training'). Under torchrun leave it out.")] = 1,
):
    """Reconstruct a radiance field from a dataset and print its held-out PSNR.

    Runs the cached stages sfm → data → envelope → tetra → init → train → bake → eval in the run
    directory (sfm only for a folder of photos); a stage re-runs only when its inputs or its config
    keys changed."""
    from radfield.pipeline import registry
    from radfield.pipeline.config import load_config
    from radfield.pipeline.info import run_info
    from radfield.pipeline.runner import run_pipeline

    if distributed_cli.follower():  # torchrun's ranks >= 1 only train, with what rank 0 sends them
        return distributed_cli.follow()
    flags = {"train.primitive": primitive, "train.max_primitives": max_primitives, "train.iterations": iterations,
             "data.downscale": downscale, "seed": seed, "device": device,
             "data.background": list(parse_background(background)) if background is not None else None,
             "envelope.source": "none" if no_cage else None}
    cfg = load_config(config, sets or [], {key: value for key, value in flags.items() if value is not None})
    resolve_device(cfg["device"])
    registry.check(cfg, input_path)
    if nproc > 1 and not distributed_cli.distributed.launched():
        return distributed_cli.launch(nproc, cfg, output)
    with distributed_cli.leading(cfg):  # rank 0 of torchrun's ranks (nothing for a single process)
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


@app.command()
def info(
    run_dir: Annotated[Path, typer.Argument(metavar="RUN", help="A run directory.")],
    as_json: Annotated[bool, typer.Option("--json", help="Machine-readable JSON (a stable interface).")] = False,
):
    """Stages done, their timings and key figures, and the main artifacts of a run."""
    import json

    from radfield.pipeline.info import format_info, run_info

    summary = run_info(run_dir)
    typer.echo(json.dumps(summary, indent=2) if as_json else format_info(summary).rstrip())


@app.command()
def render(
    model_or_run: Annotated[Path, typer.Argument(metavar="MODEL_OR_RUN", help="A .safetensors model file, or a run directory (its final model).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder for the PNG frames (created; written under a temporary name and renamed at the end).")],
    dataset: Annotated[Optional[Path], typer.Option("--dataset", "-d", help="Dataset whose cameras to render (NeRF-synthetic, nerfstudio or COLMAP). Default for a run: the dataset it trained on.")] = None,
    split: Annotated[str, typer.Option(help="Which cameras: train, val, test or all (without split files: every data.test_every-th view is test).")] = "test",
    background: Annotated[Optional[str], typer.Option(help="Background colour R,G,B in [0, 1] (default: the run's data.background, else 1,1,1).")] = None,
    downscale: Annotated[Optional[int], typer.Option(help="Render at 1/K of the dataset's resolution (default: the run's data.downscale, else 1).")] = None,
    near: Annotated[Optional[float], typer.Option(help="Near plane distance (default: the run's render.near, else 0.01).")] = None,
    device: Annotated[str, typer.Option(help="cpu or cuda.")] = "cpu",
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
    orbit: Annotated[int, typer.Option(help="Instead of the split's cameras: a turntable of this many frames around the scene (README, 'Camera paths').")] = 0,
    elevation: Annotated[float, typer.Option(help="Orbit elevation in degrees above the horizontal.")] = 20.0,
    camera_path: Annotated[Optional[Path], typer.Option(help="Instead of the split's cameras: a nerfstudio camera-path JSON (world frame).")] = None,
    video: Annotated[Optional[Path], typer.Option(help="Also write the frames as an MP4 video (bundled ffmpeg).")] = None,
    fps: Annotated[float, typer.Option(help="Video frame rate (default 30, or the camera path's).")] = 0.0,
):
    """Render every camera of a dataset split (or an orbit / a camera path) to OUTPUT/<frame name>.png.

    For a run directory every default is the run's own: its dataset, its split rule
    (data.test_every), background, downscale and near plane; explicit options win. Each pixel is
    drawn with the model's own n x n rays (its file's supersample, from render.supersample)."""
    from radfield.pipeline.runner import is_run_dir
    from radfield.delivery.render_views import render_frames

    options = {"data.downscale": downscale, "render.near": near,
               "data.background": list(parse_background(background)) if background is not None else None}
    dev = resolve_device(device)
    model = resolve_model(model_or_run)

    def path(cameras, names):  # camera paths and videos: cli/animate.py, core/geometry/camera_path.py
        nonlocal fps
        cameras, names, fps = animate_cli.path_cameras(cameras, names, orbit, elevation, camera_path, fps)
        return cameras, names

    with progress_bar(quiet) as progress:
        task = progress.add_task("rendering", total=None)
        summary = render_frames(model, model_or_run if is_run_dir(model_or_run) else None, dataset, split, output,
                                options={k: v for k, v in options.items() if v is not None}, device=dev,
                                camera_path=path if orbit or camera_path is not None else None, video=video, fps=lambda: fps or 30.0,
                                on_start=lambda n: progress.update(task, total=n, description=f"rendering {n} views"),
                                on_frame=lambda: progress.advance(task))
    typer.echo(f"rendered {summary['views']} views ({summary['width']}x{summary['height']}, {summary['primitives']} "
               f"{summary['kind']} primitives) to {output}{f' and {video}' if video is not None else ''}; "
               f"mean render time {summary['ms_per_frame']:.1f} ms/frame")


@app.command("bench-render")
def bench_render(
    primitives: Annotated[int, typer.Option(help="Number of primitives.")] = 10_000,
    width: Annotated[int, typer.Option(help="Image width.")] = 256,
    height: Annotated[int, typer.Option(help="Image height.")] = 256,
    views: Annotated[int, typer.Option(help="Cameras on an orbit.")] = 4,
    repeats: Annotated[int, typer.Option(help="Timed passes over the cameras.")] = 2,
    device: Annotated[str, typer.Option(help="cpu or cuda.")] = "cpu",
    profile: Annotated[bool, typer.Option(help="Also print the torch profiler's top costs.")] = False,
    baseline: Annotated[bool, typer.Option("--baseline", help="Also time the readable torch twins (RADFIELD_KERNELS=torch) in the same run and print the speed-up.")] = False,
):
    """Benchmark (not a test): forward and forward+backward time of neural primitives (windowed,
    as the defaults train them, and hard-edged: neural-hard) and 3D Gaussians on the same cameras
    and budgets; prints ms/frame, pairs/s and the time ratio."""
    from radfield.bench.render import run_bench

    if min(primitives, width, height, views, repeats) < 1:
        raise RadfieldError("--primitives, --width, --height, --views and --repeats must be positive")
    run_bench(primitives, width, height, views, repeats, str(resolve_device(device)), profile, echo=typer.echo,
              baseline=baseline)


app.command("bench-train")(bench_train_cli.bench_train)
app.command("bench-dist")(bench_dist_cli.bench_dist)


@app.command("demo-scene")
def demo_scene(
    name: Annotated[str, typer.Argument(help="blobs (easy), thin (sub-pixel rods), checker (high-frequency texture), objects (separate objects, a torus, thin rods; no mesh.ply, so the envelope is the visual hull), glossy (glossy and matte objects with moving specular highlights; 100 + 20 views) or studio (glossy's objects rendered like a path tracer: 8x8 jittered rays per pixel, soft shadows, moderate highlights; 100 + 20 views).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder to create (must not exist or be empty).")],
    train_views: Annotated[Optional[int], typer.Option(help="Training views (default: the scene's own, 40; glossy and studio 100).")] = None,
    test_views: Annotated[Optional[int], typer.Option(help="Held-out test views (default: the scene's own, 8; glossy and studio 20).")] = None,
    size: Annotated[int, typer.Option(help="Image width and height in pixels.")] = 64,
    seed: Annotated[int, typer.Option(help="Turns the camera spiral.")] = 0,
    exist_ok: Annotated[bool, typer.Option("--exist-ok", help="Do nothing if OUTPUT already holds this scene (same name and seed).")] = False,
):
    """Write a tiny synthetic NeRF-synthetic scene with exact ground truth (and its mesh.ply, except for objects)."""
    import json

    from radfield.datasets.synthetic import generate_scene

    if exist_ok and (output / "scene.json").is_file():
        existing = json.loads((output / "scene.json").read_text())
        if existing.get("name") == name and existing.get("seed") == seed:
            typer.echo(f"{output} already holds the {name} scene")
            return
    generate_scene(name, output, n_train=train_views, n_test=test_views, size=size, seed=seed)
    counts = {split: len(json.loads((output / f"transforms_{split}.json").read_text())["frames"]) for split in ("train", "test")}
    typer.echo(f"wrote {name}: {counts['train']} train + {counts['test']} test views of {size}x{size} to {output}")


app.command("edit")(edit_cli.edit)
app.command("animate")(animate_cli.animate)
app.command("eval")(evaluate_cli.eval_command)
app.command("bake")(evaluate_cli.bake)
app.command("bench-quality")(evaluate_cli.bench_quality)
app.command("export")(export_cli.export)
app.command("view")(view_cli.view)


def main() -> None:
    """The console entry point: every user mistake, on every command, is one line
    `radfield: error: …` on stderr and exit code 1 (a RadfieldError from the work, or a usage
    error Click finds while parsing: a wrong option type, a missing or unknown option)."""
    click = _click_exceptions()
    try:
        code = app(standalone_mode=False)
    except click.NoArgsIsHelpError as e:  # bare `radfield` or a group without a command
        typer.echo(e.ctx.get_help())
        code = 0
    except click.UsageError as e:
        command = e.ctx.command_path if e.ctx is not None else "radfield"
        message = " ".join(e.format_message().split())
        typer.echo(f"radfield: error: {message} (see '{command} --help')", err=True)
        sys.exit(1)
    except click.ClickException as e:  # e.g. a file Click could not open
        typer.echo(f"radfield: error: {' '.join(e.format_message().split())}", err=True)
        sys.exit(1)
    except RadfieldError as e:
        typer.echo(f"radfield: error: {e}", err=True)
        sys.exit(1)
    except (KeyboardInterrupt, typer.Abort):
        typer.echo("radfield: interrupted", err=True)
        sys.exit(130)
    if isinstance(code, int) and code:  # typer.Exit(code) returns its code without standalone mode
        sys.exit(code)


def _click_exceptions():
    """Click's exception classes: Typer ≥ 0.20 vendors Click as typer._click, older Typer uses Click."""
    try:
        from typer._click import exceptions
    except ImportError:
        from click import exceptions
    return exceptions


if __name__ == "__main__":
    main()
