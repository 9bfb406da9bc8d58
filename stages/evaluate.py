"""Stage "eval" and `radfield eval`: render every view of a split and measure it against the photos.

Writes `renders/<view name>.png` and `metrics.json`, whose keys are a stable interface (keys are
only ever added)::

    {"split": "test", "kind": "neural" | "gaussian",
     "psnr": dB, "ssim": s,                 # means over the views; SSIM with the 11×11 Gaussian window
     "num_primitives": P, "num_params": n, "file_size_bytes": b,
     "fps": f,                              # renders per second (rendering only, after one warm-up)
     "views": N, "width": W, "height": H,
     "per_view": [{"name", "psnr", "ssim", "seconds"}, ...]}

Renders are composited on the scene's background, as the photos are. Undistorted photos are
measured on their valid pixels only (Scene.valid_masks; radfield.core.metrics gives the rule:
PSNR over the valid pixels, SSIM over the 11×11 windows lying wholly on valid pixels).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import torch

from radfield.core.atomic import atomic_write_text
from radfield.core.errors import RadfieldError
from radfield.core.io import load_model
from radfield.core.metrics import psnr, ssim
from radfield.core.rasterize import render
from radfield.datasets.images import write_image
from radfield.stages.config import load_config
from radfield.stages.data import SCENE, Scene, load_scene, read_dataset, scene_from_json
from radfield.stages.info import MODEL_FILE, model_path, run_dataset
from radfield.stages.pipeline import CONFIG_FILE, Context, Stage, is_run_dir

METRICS = "metrics.json"
RENDERS = "renders"


def run(ctx: Context) -> dict[str, Any]:
    scene = load_scene(ctx.inputs[SCENE])
    metrics = evaluate(ctx.inputs[MODEL_FILE], scene, ctx.config["eval"]["split"], ctx.outputs[RENDERS],
                       near=ctx.config["render"]["near"], device=ctx.device, quiet=ctx.quiet)
    ctx.outputs[METRICS].write_text(json.dumps(metrics, indent=1) + "\n")
    return {key: metrics[key] for key in ("psnr", "ssim", "fps", "views")}


STAGE = Stage("eval", run, config_keys=("eval", "render.near"), inputs=(SCENE, MODEL_FILE), outputs=(METRICS, RENDERS))


def evaluate(model_file: Path, scene: Scene, split: str, renders: Path, *, near: float = 0.01,
             device: str = "cpu", quiet: bool = True) -> dict[str, Any]:
    """Render `split` of `scene` with the model into `renders/` (created) and return the metrics
    (module docstring). Everything is loaded before anything is written."""
    model = load_model(model_file, device=device)
    cameras = scene.cameras(split)
    images, _ = scene.load_images(split)
    masks = scene.valid_masks(split)
    renders.mkdir(parents=True, exist_ok=True)
    draw = torch.no_grad()(lambda camera: render(model, camera, background=scene.background, near=near).color)
    draw(cameras[0])  # warm-up, untimed: fps is the steady rate, without one-off allocations
    per_view = []
    with _progress(quiet) as progress:
        task = progress.add_task(f"evaluating {len(cameras)} {split} views", total=len(cameras))
        for k, (camera, photo) in enumerate(zip(cameras, images)):
            mask = None if masks is None else masks[k]
            start = time.perf_counter()
            color = draw(camera).clamp(0, 1).cpu()
            seconds = time.perf_counter() - start
            write_image(renders / f"{camera.name}.png", color.numpy())
            per_view.append({"name": camera.name, "psnr": float(psnr(color, photo, mask)),
                             "ssim": float(ssim(color, photo, mask=mask)), "seconds": seconds})
            progress.advance(task)
    count = len(per_view)
    return {
        "split": split,
        "kind": model.kind,
        "psnr": sum(v["psnr"] for v in per_view) / count,
        "ssim": sum(v["ssim"] for v in per_view) / count,
        "num_primitives": len(model),
        "num_params": model.num_params(),
        "file_size_bytes": Path(model_file).stat().st_size,
        "fps": count / sum(v["seconds"] for v in per_view),
        "views": count,
        "width": cameras[0].width,
        "height": cameras[0].height,
        "per_view": per_view,
    }


def eval_report(target: Path, dataset: Path | None, split: str, out_dir: Path, *,
                options: dict[str, Any] | None = None, device: str = "cpu", quiet: bool = True) -> dict[str, Any]:
    """`radfield eval`: evaluate a model file, or a run's final model, on `dataset` (default: the
    run's input, or its SfM output when the input was photos) into `out_dir`/{renders/, metrics.json}. The data settings (downscale, background)
    are the run's, else the defaults, overridden by `options` ({"data.downscale": 2, ...})."""
    target = Path(target)
    run_dir = target if is_run_dir(target) else None
    model = model_path(target) if run_dir else target
    if not model.is_file():
        raise RadfieldError(f"{target}: run directory has no trained model yet" if run_dir
                            else f"{target}: no such model file or run directory")
    config = load_config(run_dir / CONFIG_FILE if run_dir else None, options=options or {})
    if dataset is None:
        dataset = run_dataset(run_dir) if run_dir else None
        if dataset is None:
            raise RadfieldError("--dataset is required to evaluate a model file")
    if out_dir.exists() and not out_dir.is_dir():
        raise RadfieldError(f"{out_dir}: exists and is not a folder")
    scene = scene_from_json(read_dataset(dataset, config["data"])[0], dataset)
    metrics = evaluate(model, scene, split, out_dir / RENDERS, near=config["render"]["near"], device=device,
                       quiet=quiet)
    atomic_write_text(out_dir / METRICS, json.dumps(metrics, indent=1) + "\n")
    return metrics


def _progress(quiet: bool):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                    disable=quiet, transient=True)
