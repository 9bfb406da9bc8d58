"""Stage "train": optimise the initial primitives against the training views.

Inputs: scene.json (data stage) and init.safetensors (init stage). Outputs in RUN/train/:
model.safetensors, the trained model in the dataset's own world frame (radfield.model_file format;
with render.supersample > 1 its metadata records n, so every later render of the file draws it so);
log.jsonl, one JSON record per step (radfield.core.trainer.log: step, loss,
train PSNR, primitives, seconds, population control, and test_psnr, the held-out views' PSNR
every `train.eval_every` steps and at the last, for information only); curves.png, the log
drawn; final_state.safetensors, the full training state at the last step (a checkpoint). The log
and the progress bar get the steps' records when the trainer reads them off the device, every
`train.log_every` steps (by default every step on the CPU, every 50 on a GPU) and at refinement,
held-out, checkpoint and last steps: the same records whatever `log_every` is, but for "seconds",
the time the record was read.

Training runs in the normalised frame of scene.json, x_norm = (x − center) · scale: means shift
and scale, log-scales gain log(scale), camera centres and the near plane move alike; rotations,
SH, the density MLP (optical depth is measured in units of max(s)) and Gaussian opacities are
unchanged. The saved model is mapped back, so it renders the dataset's cameras as trained.
Undistorted photos are trained on their valid pixels only (Scene.valid_masks). The SH degree
trained is the init model's: train.sh_degree, unless the kind chooses its own (the relightable
kinds: degree 0, eq. 14's constant colour; kinds/relight.py).

Every `train.checkpoint_every` steps the full training state goes to RUN/train.work/; a run that
was killed resumes from there and ends exactly where an uninterrupted run would have. Raising
`train.iterations` (and nothing else) on a finished run continues from final_state.safetensors
instead of starting over (radfield.core.trainer.loop explains the learning-rate schedule then).

Under torchrun (or `radfield reconstruct --nproc N`) this stage runs on rank 0 and the training
itself on every rank (radfield.core.trainer.dataparallel); the outputs are rank 0's, written as above.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from radfield.model_file import load_model, save_model
from radfield.core.kinds import Primitives
from radfield.core.trainer.dataparallel import train_on_ranks
from radfield.core.trainer.loop import checkpoint_header, load_checkpoint, mean_psnr, save_checkpoint
from radfield.core.trainer.log import TrainLog, plot_curves, read_log
from radfield.util.progress import progress_bar
from radfield.stages.data import DATA_KEYS, SCENE, Normalization, load_scene
from radfield.stages.init import INIT_MODEL
from radfield.pipeline.runner import Context, Stage
from radfield.pipeline.schema import RenderConfig
from radfield import run as layout

MODEL_FILE = layout.MODEL_FILE  # the trained model, the run's final one (radfield.run.Run.model)
LOG = layout.LOG_FILE
CURVES = layout.CURVES_FILE
FINAL_STATE = "final_state.safetensors"
CHECKPOINT = layout.CHECKPOINT_FILE  # in RUN/train.work/ (radfield.run.Run.checkpoint)


def run(ctx: Context) -> dict[str, Any]:
    render = RenderConfig.from_dict(ctx.config["render"])
    supersample = render.supersample  # rays per pixel side, in training and its measurements
    scene = load_scene(ctx.inputs[SCENE])
    norm = scene.normalization
    cameras = [norm.camera(camera) for camera in scene.train_cameras]  # a RadfieldError for unposed photos
    (images, alphas), masks = scene.load_images("train"), scene.valid_masks("train")
    prims = to_normalized(load_model(ctx.inputs[INIT_MODEL]), norm)
    # the SH degree the init stage gave the model: train.sh_degree, or the kind's own (kinds/relight.py)
    cfg = {**ctx.config["train"], "supersample": supersample, "sh_degree": prims.sh_degree}
    near = render.near * norm.scale
    held_out = None
    if cfg["eval_every"] > 0 and scene.splits.get("test"):
        test_cameras, test_images = [norm.camera(c) for c in scene.test_cameras], scene.test_images()
        test_masks = scene.valid_masks("test")
        held_out = lambda p: mean_psnr(p, test_cameras, test_images, background=scene.background, near=near,
                                       masks=test_masks, supersample=supersample)
    key = _continue_key(ctx)
    start, records = _starting_point(ctx, key)
    first_step = start.step if start is not None else 0

    clock = time.perf_counter()
    with _TrainProgress(cfg["iterations"], first_step, ctx.quiet) as progress, \
            TrainLog(ctx.work / LOG, records) as log:
        base = log.seconds

        def on_step(step: int, info: dict) -> None:
            progress.update(step, info)
            log.write({"step": step, **info, "seconds": round(base + time.perf_counter() - clock, 3)})

        state = train_on_ranks(prims, cameras, images, cfg, background=scene.background,
                               extent=scene.extent * norm.scale, seed=ctx.seed, device=ctx.device, near=near,
                               start_state=start, masks=masks, alphas=alphas, on_step=on_step, held_out=held_out,
                               checkpoint=lambda snapshot: save_checkpoint(ctx.work / CHECKPOINT, snapshot, key))
    steps_run = state.step - first_step
    seconds = time.perf_counter() - clock

    trained = replace(state.primitives(), supersample=supersample)  # the model records its n (model_file.py)
    train_psnr = mean_psnr(trained, cameras, images, background=scene.background, near=near, masks=masks)
    model = to_world(trained, norm)
    save_model(ctx.outputs[MODEL_FILE], model)
    save_checkpoint(ctx.outputs[FINAL_STATE], state, key)
    shutil.copyfile(ctx.work / LOG, ctx.outputs[LOG])
    plot_curves(read_log(ctx.outputs[LOG]), ctx.outputs[CURVES], title=f"{ctx.run_dir.name}: {model.kind} primitives")
    held = [r["test_psnr"] for r in read_log(ctx.outputs[LOG]) if r.get("test_psnr") is not None]
    return {
        "primitives": len(model),
        "params": model.num_params(),
        "iterations": state.step,
        "train_psnr": train_psnr,
        "seconds_per_iteration": seconds / steps_run if steps_run else None,
        "continued_from": first_step,
        "last_test_psnr": held[-1] if held else None,
        "supersample": supersample,   # rays per pixel side the model is drawn with (radfield info shows it)
        "window": getattr(model, "window", False),   # neural: the density window (render.window)
    }


STAGE = Stage("train", run, config_keys=("train", "render", *DATA_KEYS, "seed"), inputs=(SCENE, INIT_MODEL),
              outputs=(MODEL_FILE, LOG, CURVES, FINAL_STATE), version=3)


def _starting_point(ctx: Context, key: dict):
    """(state to start from or None, the log records before it): the checkpoint of an interrupted
    attempt, else the final state of the previous run when it differs from this one only by fewer
    iterations (continuing), else a fresh start."""
    checkpoint = ctx.work / CHECKPOINT
    if checkpoint.is_file() and checkpoint_header(checkpoint).get("note") == key:  # (the pipeline wipes others)
        start = load_checkpoint(checkpoint)
        ctx.log(f"resuming from the checkpoint at step {start.step}")
        return start, [r for r in read_log(ctx.work / LOG) if r["step"] <= start.step]
    final = ctx.stage_dir / FINAL_STATE
    if final.is_file():
        header = checkpoint_header(final)
        if header.get("note") == key and header["step"] < ctx.config["train"]["iterations"]:
            ctx.log(f"continuing the finished run from step {header['step']}")
            return load_checkpoint(final), [r for r in read_log(ctx.stage_dir / LOG) if r["step"] <= header["step"]]
    return None, []


def _continue_key(ctx: Context) -> dict:
    """What a saved state is valid for: everything the stage depends on except train.iterations
    and train.log_every (which changes no value; without it the key is that of the runs made
    before the key existed) (its config sections and the content of its inputs)."""
    config = json.loads(json.dumps(ctx.config))
    del config["train"]["iterations"]
    config["train"].pop("log_every", None)
    inputs = {name: None if path is None else hashlib.sha256(Path(path).read_bytes()).hexdigest()
              for name, path in sorted(ctx.inputs.items())}
    return {"config": hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest(), "inputs": inputs}


def to_normalized(prims: Primitives, norm: Normalization) -> Primitives:
    """World-frame primitives in the normalised frame x_norm = (x − center) · scale."""
    return replace(prims, means=norm.apply(prims.means), log_scales=prims.log_scales + math.log(norm.scale))


def to_world(prims: Primitives, norm: Normalization) -> Primitives:
    """Inverse of to_normalized."""
    return replace(prims, means=norm.invert(prims.means), log_scales=prims.log_scales - math.log(norm.scale))


class _TrainProgress:
    """The training's progress (util/progress.py) with loss, PSNR, primitive count and it/s."""

    def __init__(self, iterations: int, first_step: int, quiet: bool):
        self.first_step = first_step
        self.progress = progress_bar(quiet, stats=True)
        self.task = self.progress.add_task("training", total=iterations, completed=first_step, stats="")
        self.clock = time.perf_counter()

    def __enter__(self) -> "_TrainProgress":
        self.progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.progress.__exit__(*exc)

    def update(self, step: int, info: dict) -> None:
        rate = (step - self.first_step) / max(time.perf_counter() - self.clock, 1e-9)
        stats = f"loss {info['loss']:.4f}  PSNR {info['psnr']:.2f}  {info['primitives']} prims  {rate:.1f} it/s"
        self.progress.update(self.task, completed=step, stats=stats)
