"""`radfield render`: a model's or a run's frames of a dataset split, an orbit or a camera path
(radfield.delivery.render_views)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield.cli.common import (Force, check_options, check_output, condition_options, parse_background, progress_bar,
                                 resolve_device, resolve_model)
from radfield.util.ranges import AT_LEAST_0, AT_LEAST_1, ELEVATION, POSITIVE


@condition_options("render")
def render(
    model_or_run: Annotated[Path, typer.Argument(metavar="MODEL_OR_RUN", help="A model file (radfield's .safetensors, or any format `radfield import` reads: a 3DGS PLY, .spz, .splat, .glb, a Splat the Net PLY), or a run directory (its final model).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder for the PNG frames (created; written under a temporary name and renamed at the end; an existing non-empty one needs --force).")],
    dataset: Annotated[Optional[Path], typer.Option("--dataset", "-d", help="Dataset whose cameras to render (NeRF-synthetic, nerfstudio or COLMAP). Default for a run: the dataset it trained on.")] = None,
    split: Annotated[str, typer.Option(help="Which cameras: train, val, test or all (without split files: every data.test_every-th view is test).")] = "test",
    background: Annotated[Optional[str], typer.Option(help="Background colour R,G,B in [0, 1] (default: the run's data.background, else 1,1,1).")] = None,
    downscale: Annotated[Optional[int], typer.Option(help="Render at 1/K of the dataset's resolution (default: the run's data.downscale, else automatic: 1, or what data.max_size needs).")] = None,
    near: Annotated[Optional[float], typer.Option(help="Near plane distance (default: the run's render.near, else 0.01).")] = None,
    device: Annotated[str, typer.Option(help="cpu or cuda.")] = "cpu",
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
    orbit: Annotated[int, typer.Option(help="Instead of the split's cameras: a turntable of this many frames around the scene (docs/usage.md, 'Camera paths').")] = 0,
    elevation: Annotated[float, typer.Option(help="Orbit elevation in degrees above the horizontal.")] = 20.0,
    camera_path: Annotated[Optional[Path], typer.Option(help="Instead of the split's cameras: a nerfstudio camera-path JSON (world frame).")] = None,
    video: Annotated[Optional[Path], typer.Option(help="Also write the frames as an MP4 video (bundled ffmpeg).")] = None,
    fps: Annotated[Optional[float], typer.Option(help="Video frame rate.", show_default="30, or the camera path's")] = None,
    camera: Annotated[Optional[str], typer.Option("--camera", help="Only this view of the split (its frame name, or its index): e.g. the fixed camera of a time-lapse (--times).")] = None,
    asked=None,   # the view conditions' options (cli/common.condition_options: --time, --light, ...)
    force: Force = False,
):
    """Render a model's views of a dataset split, an orbit or a camera path to PNGs.

    Every camera of the split (or of the orbit or the path) becomes OUTPUT/<frame name>.png.

    For a run directory every default is the run's own: its dataset, its split rule
    (data.test_every), background, downscale and near plane; explicit options win. Each pixel is
    drawn with the model's own n x n rays (its file's supersample, from render.supersample).

    A dynamic model (a dynamic dataset's run) draws each view at its own time, or at --time T, or
    at the --times A:B:N; a time-lapse video: --camera NAME (or --orbit N) with --times and --video.

    A relightable model (a relighting dataset's run) draws each view under its own light, or under
    --light X,Y,Z / --light-dir X,Y,Z, or under --light-orbit N lights; a video of the light going
    round: --camera NAME (or --orbit N) with --light-orbit and --video."""
    from radfield.delivery.render_views import render_frames
    from radfield.run import is_run_dir

    check_options({"--downscale": (downscale, AT_LEAST_1), "--near": (near, POSITIVE), "--orbit": (orbit, AT_LEAST_0),
                   "--elevation": (elevation, ELEVATION), "--fps": (fps, POSITIVE)})
    options = {"data.downscale": downscale, "render.near": near,
               "data.background": list(parse_background(background)) if background is not None else None}
    check_output(output, force, folder=True)
    if video is not None:
        check_output(video, force, folder=False)
    dev = resolve_device(device)
    model = resolve_model(model_or_run)
    with progress_bar(quiet) as progress:
        task = progress.add_task("rendering", total=None)
        summary = render_frames(model, model_or_run if is_run_dir(model_or_run) else None, dataset, split, output,
                                options={k: v for k, v in options.items() if v is not None}, device=dev,
                                orbit=orbit, elevation=elevation, camera_path=camera_path, video=video, fps=fps or 0.0,
                                camera=camera, asked=asked,
                                on_start=lambda n: progress.update(task, total=n, description=f"rendering {n} images"),
                                on_frame=lambda: progress.advance(task))
    typer.echo(f"rendered {what_was_drawn(summary)} ({summary['width']}x{summary['height']}, {summary['primitives']} "
               f"{summary['kind']} primitives) to {output}{f' and {video}' if video is not None else ''}; "
               f"mean render time {summary['ms_per_frame']:.1f} ms/frame")


def what_was_drawn(summary: dict) -> str:
    """'8 views', '4 views at 1 moment', or where a view has several images '96 images: 4 views at
    24 moments' (a dynamic dataset's cameras at their moments; 1 view under 40 lights)."""
    from radfield import conditions

    plural = lambda n, word: f"{n} {word}{'s' if n != 1 else ''}"
    views = plural(summary["views"], "view")
    for name, count in summary["drawn_under"].items():
        preposition, noun = conditions.get(name).drawn
        views += f" {preposition} {plural(count, noun)}"
    return views if summary["images"] == summary["views"] else f"{plural(summary['images'], 'image')}: {views}"
