"""Stage "bake" and `radfield bake RUN -o MODEL`: the delivery form of a trained model.

Prunes the primitives whose transmittance-weighted alpha stays below `bake.min_weight` in every
training view (radfield.delivery.bake), optionally stores float16 tensors (`bake.fp16`), and writes
one model file (radfield.model_file format) whose metadata says how it was made::

    "baked": {"source": "<file name>", "source_sha256": "...", "min_weight": τ, "fp16": bool,
              "primitives_before": P0, "primitives_after": P1}

The baked model keeps the source's `supersample` (prims.supersample): coverage and PSNR are
measured with its n × n rays per pixel, as every render of the model draws it.

Figures (manifest / `radfield info`): primitives and file sizes before and after, and the PSNR of
the `eval.split` views before and after with its change (as the baked file renders, float16
included). The eval stage still measures the trained model; this stage measures what it changed.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import torch

from radfield.delivery.bake import coverage, prune, to_fp16_and_back
from radfield.util.progress import progress_bar
from radfield.model_file import load_model, save_model
from radfield.core.trainer.loop import mean_psnr
from radfield.datasets.scene import SCENE, Scene, load_scene
from radfield.pipeline.runner import Context, Stage
from radfield.pipeline.schema import BakeConfig
from radfield.stages.train import MODEL_FILE

BAKED = "baked.safetensors"


def run(ctx: Context) -> dict[str, Any]:
    bake = BakeConfig.from_dict(ctx.config["bake"])
    return bake_model(ctx.inputs[MODEL_FILE], load_scene(ctx.inputs[SCENE]), ctx.outputs[BAKED],
                      min_weight=bake.min_weight, fp16=bake.fp16, split=ctx.config["eval"]["split"],
                      near=ctx.config["render"]["near"], device=ctx.device, quiet=ctx.quiet)


STAGE = Stage("bake", run, config_keys=("bake", "eval.split", "render.near"), inputs=(SCENE, MODEL_FILE),
              outputs=(BAKED,), version=2)   # 2: conditioned kinds measured as each view draws them


def bake_model(model_file: Path, scene: Scene, out: Path, *, min_weight: float, fp16: bool, split: str,
               near: float = 0.01, device: str = "cpu", quiet: bool = True) -> dict[str, Any]:
    """Bake `model_file` against `scene`'s training views into `out`; returns the figures."""
    model = load_model(model_file, device=device)
    train_cameras = scene.train_cameras
    held_out, photos = scene.cameras(split), scene.load_images(split)[0]
    with progress_bar(quiet) as progress:
        task = progress.add_task(f"coverage in {len(train_cameras)} training views", total=len(train_cameras))
        weights = coverage(model, train_cameras, background=scene.background, near=near,
                           on_view=lambda: progress.advance(task))
    baked, keep = prune(model, weights, min_weight)
    if fp16:
        baked = to_fp16_and_back(baked)
    source = Path(model_file).read_bytes()
    recipe = {"source": Path(model_file).name, "source_sha256": hashlib.sha256(source).hexdigest(),
              "min_weight": min_weight, "fp16": fp16, "primitives_before": len(model), "primitives_after": len(baked)}
    save_model(out, baked.to("cpu"), extra={"baked": json.dumps(recipe, sort_keys=True)},
               dtype=torch.float16 if fp16 else torch.float32)
    # over the valid pixels, as eval scores (undistorted photos have an invalid border)
    masks = scene.valid_masks(split)
    before = mean_psnr(model, held_out, photos.to(device), background=scene.background, near=near, masks=masks)
    after = mean_psnr(baked, held_out, photos.to(device), background=scene.background, near=near, masks=masks)
    return {"primitives_before": len(model), "primitives_after": len(baked), "pruned": int((~keep).sum()),
            "size_before": len(source), "size_after": Path(out).stat().st_size, "fp16": fp16,
            "psnr_before": before, "psnr_after": after, "psnr_change": after - before, "split": split}
