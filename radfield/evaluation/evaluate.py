"""The evaluation of a model on a dataset split, which stage "eval" and `radfield eval` run: render
every view of the split and measure it against the photos.

Writes `renders/<view name>.png` and `metrics.json`, whose keys are a stable interface (keys are
only ever added)::

    {"split": "test", "kind": "neural" | "gaussian",
     "psnr": dB, "ssim": s,                 # means over the views; SSIM with the 11×11 Gaussian window
     "num_primitives": P, "num_params": n, "file_size_bytes": b,
     "fps": f,                              # renders per second (rendering only, after one warm-up)
     "views": N, "width": W, "height": H,
     "per_view": [{"name", "psnr", "ssim", "seconds", "lpips"(, "time")(, "light")}, ...],
     "per_<condition>": [...],              # for each view condition the views carry (radfield/conditions),
                                            # each value's views averaged (evaluation/metrics.per_condition):
     "per_time": [{"time", "views", "psnr", "ssim", "lpips"}, ...],   # a dynamic scene, each moment ξ_t
     "per_light": [{"position" | "direction", "intensity", "views", "psnr", "ssim", "lpips"}, ...],
                                            # a one-light-at-a-time capture, each light (world frame)
     "lpips": l | null,                     # AlexNet LPIPS v0.1 (radfield.evaluation.lpips), mean over the views;
     "lpips_note": "why lpips is null"}     # null when the weights are not installed or the images are
                                            # smaller than 31×31 (then lpips_note says which)

Renders are composited on the scene's background, as the photos are. Undistorted photos are
measured on their valid pixels only (Scene.valid_masks; radfield.evaluation.metrics gives the rule:
PSNR over the valid pixels, SSIM over the 11×11 windows lying wholly on valid pixels).

Besides metrics.json and renders/, it writes (radfield.evaluation.report) `report.md` (the tables),
`grids/<view name>.png` (ground truth | render | error map), `training/` (a copy of the run's
train/curves.png and train/log.jsonl, when the run has them) and `figures/` (for a dynamic scene,
psnr_over_time.png; for a one-light-at-a-time capture, psnr_per_light.png; empty otherwise).

A view's conditions (Camera.conditions: a dynamic scene's moment, a capture's light) go with it: a
conditioned model is drawn under the view's own (the kind's at_view), each per-view entry records
them (scene.json's form, world frame), and per_<condition> and the report's section of each (the
"Over time" plot and table, the "Per light" plot and table) average the views of each value. A
static model is drawn as it is under every light: the light-blind baseline's run (data.light
ignore) has no lights in its views, but its model file measured on the dataset (`radfield eval
MODEL --dataset`) gets the same table.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Any

import torch

from radfield import run as layout
from radfield.core.geometry.camera_path import orbit_from_cameras
from radfield.core.render.antialias import render_model
from radfield import conditions
from radfield.datasets.images import write_image
from radfield.datasets.scene import Scene, read_dataset, scene_from_json
from radfield.errors import RadfieldError
from radfield.evaluation import lpips as lpips_metric
from radfield.evaluation import report
from radfield.evaluation.metrics import per_condition, psnr, ssim
from radfield.model_file import read_metadata
from radfield.model_formats import detect, load as load_model
from radfield.pipeline.config import load_config
from radfield.run import MODEL_STAGE, Run, is_run_dir
from radfield.util.atomic import atomic_folder, atomic_write_bytes, atomic_write_text
from radfield.util.progress import progress_bar

METRICS = layout.METRICS_FILE


RENDERS = "renders"


REPORT = "report.md"


GRIDS = "grids"


TRAINING = "training"


FIGURES = report.FIGURES


TRAIN_CURVES = (layout.CURVES_FILE, layout.LOG_FILE)  # written by the train stage into RUN/train/, when it logs


def check_supersample(model_file: Path, trained_with: int) -> None:
    """The run's model draws with its own n (the file's `supersample`); a file that disagrees with the
    run's render.supersample was trained before model files recorded n, and would be measured at
    the wrong n: an error rather than a silently lower PSNR."""
    recorded = load_model(model_file).supersample
    if recorded != trained_with:
        raise RadfieldError(f"{model_file}: records supersample={recorded} but the run trained with "
                            f"render.supersample={trained_with} (a model from before model files recorded it): "
                            f"retrain it with --force train")


def evaluate(model_file: Path, scene: Scene, split: str, renders: Path, *, near: float = 0.01,
             device: str = "cpu", quiet: bool = True, grids: Path | None = None) -> dict[str, Any]:
    """Render `split` of `scene` with the model, as it was trained (its own n × n rays a pixel,
    core/antialias.render_model), into `renders/` (created) and return the metrics (module
    docstring); with `grids`, also the grid images there. Everything is loaded before anything
    is written."""
    model = load_model(model_file, device=device)
    cameras = scene.cameras(split)
    images, _ = scene.load_images(split)
    masks = scene.valid_masks(split)
    lpips_net, lpips_note = _lpips_network(device, cameras[0])
    renders.mkdir(parents=True, exist_ok=True)
    if grids is not None:
        grids.mkdir(parents=True, exist_ok=True)
    draw = torch.no_grad()(lambda camera: render_model(model, camera, background=scene.background, near=near).color)
    draw(cameras[0])  # warm-up, untimed: fps is the steady rate, without one-off allocations
    per_view = []
    with progress_bar(quiet) as progress:
        task = progress.add_task(f"evaluating {len(cameras)} {split} views", total=len(cameras))
        for k, (camera, photo) in enumerate(zip(cameras, images)):
            mask = None if masks is None else masks[k]
            start = time.perf_counter()
            color = draw(camera).clamp(0, 1).cpu()
            seconds = time.perf_counter() - start
            write_image(renders / f"{camera.name}.png", color.numpy())
            per_view.append({"name": camera.name, "psnr": float(psnr(color, photo, mask)),
                             "ssim": float(ssim(color, photo, mask=mask)), "seconds": seconds,
                             **conditions.view_json(camera.conditions)})
            # LPIPS sees the photo in the invalid pixels (a render there is never judged)
            judged = color if mask is None else torch.where(mask[..., None].cpu(), color, photo.cpu())
            per_view[-1]["lpips"] = lpips_metric.lpips(judged, photo, lpips_net) if lpips_net is not None else None
            if grids is not None:
                write_image(grids / f"{camera.name}.png", report.view_grid(photo.cpu().numpy(), color.numpy()))
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
        "lpips": None if lpips_net is None else sum(v["lpips"] for v in per_view) / count,
        **({"lpips_note": lpips_note} if lpips_net is None else {}),
        **{f"per_{c.name}": per_condition(per_view, c) for c in conditions.registered()
           if any(c.name in v for v in per_view)},
    }


def _lpips_network(device: str, camera) -> tuple[lpips_metric.AlexLPIPS | None, str | None]:
    """The LPIPS network, or None and the reason it cannot be used for these views."""
    if min(camera.width, camera.height) < lpips_metric.MIN_SIZE:
        return None, f"images of {camera.width}×{camera.height} are smaller than LPIPS' {lpips_metric.MIN_SIZE}×{lpips_metric.MIN_SIZE}"
    try:
        return lpips_metric.load_network(device), None
    except lpips_metric.Unavailable as e:
        return None, str(e)


def write_report(out_dir: Path, metrics: dict[str, Any], *, model: str, run_dir: Path | None,
                 cameras: list | None = None) -> None:
    """report.md, training/ and figures/ in `out_dir` (beside metrics.json and grids/); `cameras`,
    the measured views, place the lights of the per-light plot about the object (their focus and
    mean up, as a light orbit does)."""
    (out_dir / FIGURES).mkdir(parents=True, exist_ok=True)
    if metrics.get("per_time"):
        atomic_write_bytes(out_dir / report.TIME_PLOT, report.time_plot(metrics["per_time"]))
    if metrics.get("per_light"):
        frame = orbit_from_cameras(cameras) if cameras else {"target": (0.0, 0.0, 0.0), "up": (0.0, 0.0, 1.0)}
        atomic_write_bytes(out_dir / report.LIGHT_PLOT, report.light_plot(metrics["per_light"], frame["target"],
                                                                           frame["up"]))
    curves = []
    (out_dir / TRAINING).mkdir(parents=True, exist_ok=True)
    for name in TRAIN_CURVES:
        source = Run(run_dir).artifact(MODEL_STAGE, name) if run_dir is not None else None
        if source is not None and source.is_file():
            shutil.copyfile(source, out_dir / TRAINING / name)
            curves.append(f"{TRAINING}/{name}")
    text = report.report_markdown(metrics, model=model, grids_dir=GRIDS if (out_dir / GRIDS).is_dir() else None,
                                  curves=curves)
    atomic_write_text(out_dir / REPORT, text)


def eval_report(target: Path, dataset: Path | None, split: str, out_dir: Path, *,
                options: dict[str, Any] | None = None, device: str = "cpu", quiet: bool = True) -> dict[str, Any]:
    """`radfield eval`: evaluate a model file, or a run's final model, on `dataset` (default: the
    run's input, or its SfM output when the input was photos) into `out_dir`/{renders/, metrics.json}. The data settings (downscale, background)
    are the run's, else the defaults, overridden by `options` ({"data.downscale": 2, ...})."""
    model, scene, run_dir, config = resolve_target(target, dataset, options)
    if out_dir.exists() and not out_dir.is_dir():
        raise RadfieldError(f"{out_dir}: exists and is not a folder")
    with atomic_folder(out_dir, merge=True) as tmp:
        metrics = evaluate(model, scene, split, tmp / RENDERS, near=config["render"]["near"], device=device,
                           quiet=quiet, grids=tmp / GRIDS)
        atomic_write_text(tmp / METRICS, json.dumps(metrics, indent=1) + "\n")
        write_report(tmp, metrics, model=str(model), run_dir=run_dir, cameras=scene.cameras(split))
    return metrics


def resolve_target(target: Path, dataset: Path | None, options: dict[str, Any] | None = None):
    """(model file, Scene, run dir or None, config) of a run directory or a model file."""
    target = Path(target)
    run = Run(target) if is_run_dir(target) else None
    model = run.model if run else target
    if not model.is_file():
        raise RadfieldError(f"{target}: run directory has no trained model yet" if run
                            else f"{target}: no such model file or run directory")
    config = load_config(run.config_file if run else None, options=options or {})
    if dataset is None:
        dataset = run.dataset() if run else None
        if dataset is None:
            raise RadfieldError("--dataset is required to evaluate a model file")
    scene_json = read_dataset(dataset, config["data"])[0]
    scene_json = conditions.without_ignored(scene_json, config["data"])   # as the run's data stage saw the views
    scene = scene_from_json(scene_json, dataset)
    check_conditions(model, scene, dataset)
    return model, scene, target if run else None, config


def check_conditions(model_file: Path, scene: Scene, dataset: Path) -> None:
    """A conditioned model (kinds/dynamic.py, kinds/relight.py) is drawn at each view's time or
    under its light: a dataset whose views carry none cannot measure it (one line, before anything
    is rendered or written). A static model on such views is measured as it is (the data.time /
    data.light ignore baselines)."""
    from radfield.core import kinds

    # the other formats hold static kinds only (Gaussians; stn-ply: neural primitives)
    kind = read_metadata(model_file).get("kind") if detect(model_file).name == "radfield" else None
    carried = conditions.view_conditions(scene.splits)
    for condition in kinds.get(kind).conditions if kind in kinds.names() else ():
        if condition not in carried:
            raise RadfieldError(f"{model_file}: a {conditions.get(condition).kind_words} model ({kind}) is measured on "
                                f"views that carry a {condition}, but the views of {dataset} carry no {condition}")
