"""Stage "train": optimise the initial primitives against the training views.

Inputs: scene.json (data stage) and init.safetensors (init stage). Output: model.safetensors, the
trained model in the dataset's own world frame (radfield.core.io format).

Training runs in the normalised frame of scene.json, x_norm = (x − center) · scale: means shift
and scale, log-scales gain log(scale), camera centres and the near plane move alike; rotations,
SH, the density MLP (optical depth is measured in units of max(s)) and Gaussian opacities are
unchanged. The saved model is mapped back, so it renders the dataset's cameras as trained.

Every `train.checkpoint_every` steps the full training state goes to RUN/train.work/; a run that
was killed resumes from there and ends exactly where an uninterrupted run would have.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from radfield.core.io import load_model, save_model
from radfield.core.primitives import Gaussians, NeuralPrimitives
from radfield.core.trainer import load_checkpoint, mean_psnr, save_checkpoint, train
from radfield.stages.data import SCENE, Normalization, load_scene
from radfield.stages.info import MODEL_FILE
from radfield.stages.init import INIT_MODEL
from radfield.stages.pipeline import Context, Stage
from radfield.core.cage import CAGE_NPZ, write_binding

CHECKPOINT = "checkpoint.safetensors"
MODEL_BINDING = "model_binding.npz"  # per trained primitive: its cage tet and barycentric coordinates


def run(ctx: Context) -> dict[str, Any]:
    cfg = ctx.config["train"]
    scene = load_scene(ctx.inputs[SCENE])
    world_cameras = scene.train_cameras  # a RadfieldError for unposed photos
    norm = scene.normalization
    cameras = [norm.camera(camera) for camera in world_cameras]
    images = scene.train_images()
    prims = to_normalized(load_model(ctx.inputs[INIT_MODEL]), norm)
    near = ctx.config["render"]["near"] * norm.scale
    checkpoint = ctx.work / CHECKPOINT
    start = load_checkpoint(checkpoint) if checkpoint.is_file() else None
    if start is not None:
        ctx.log(f"resuming from the checkpoint at step {start.step}")
    first_step = start.step if start is not None else 0

    clock = time.perf_counter()
    with _TrainProgress(cfg["iterations"], first_step, ctx.quiet) as progress:
        state = train(prims, cameras, images, cfg, background=scene.background, extent=scene.extent * norm.scale,
                      seed=ctx.seed, device=ctx.device, near=near, start_state=start, on_step=progress.update,
                      checkpoint=lambda snapshot: save_checkpoint(checkpoint, snapshot))
    steps_run = state.step - first_step
    seconds = time.perf_counter() - clock

    trained = state.primitives()
    train_psnr = mean_psnr(trained, cameras, images, background=scene.background, near=near)
    model = to_world(trained, norm)
    save_model(ctx.outputs[MODEL_FILE], model)
    # the editor moves primitives with the cage: bind the trained centres, as init bound its own
    write_binding(ctx.outputs[MODEL_BINDING], model.means.numpy(), ctx.inputs[CAGE_NPZ])
    return {
        "primitives": len(model),
        "params": model.num_params(),
        "iterations": state.step,
        "train_psnr": train_psnr,
        "seconds_per_iteration": seconds / steps_run if steps_run else None,
    }


STAGE = Stage("train", run, config_keys=("train", "render", "data", "seed"), inputs=(SCENE, INIT_MODEL, CAGE_NPZ),
              outputs=(MODEL_FILE, MODEL_BINDING), version=2)


def to_normalized(prims: NeuralPrimitives | Gaussians, norm: Normalization) -> NeuralPrimitives | Gaussians:
    """World-frame primitives in the normalised frame x_norm = (x − center) · scale."""
    return replace(prims, means=norm.apply(prims.means), log_scales=prims.log_scales + math.log(norm.scale))


def to_world(prims: NeuralPrimitives | Gaussians, norm: Normalization) -> NeuralPrimitives | Gaussians:
    """Inverse of to_normalized."""
    return replace(prims, means=norm.invert(prims.means), log_scales=prims.log_scales - math.log(norm.scale))


class _TrainProgress:
    """A rich progress bar with loss, PSNR, primitive count and it/s (nothing when quiet)."""

    def __init__(self, iterations: int, first_step: int, quiet: bool):
        self.first_step = first_step
        self.progress = Progress(TextColumn("training"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn("{task.fields[stats]}"), TimeRemainingColumn(),
                                 disable=quiet, transient=True)
        self.task = self.progress.add_task("train", total=iterations, completed=first_step, stats="")
        self.clock = time.perf_counter()

    def __enter__(self) -> "_TrainProgress":
        self.progress.start()
        return self

    def __exit__(self, *exc) -> None:
        self.progress.stop()

    def update(self, step: int, info: dict) -> None:
        rate = (step - self.first_step) / max(time.perf_counter() - self.clock, 1e-9)
        stats = f"loss {info['loss']:.4f}  PSNR {info['psnr']:.2f}  {info['primitives']} prims  {rate:.1f} it/s"
        self.progress.update(self.task, completed=step, stats=stats)
