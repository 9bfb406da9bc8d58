"""After training, drop the primitives that lie inside the frusta of fewer than K training views
(K = 0, 2, 3, 4, 6) and print the val and test PSNR of what is left, per run.
    usage: .venv/bin/python scripts/study/few_view_prune.py RUN..."""
import sys
from pathlib import Path

import torch

from radfield.core.render.antialias import render_model
from radfield.model_file import load_model
from radfield.evaluation.metrics import psnr
from radfield.core.train.strategy import in_frustum
from radfield.datasets.scene import load_scene


def mean_psnr(model, cameras, images, background) -> float:
    return sum(float(psnr(render_model(model, c, background=background).color.clamp(0, 1), img))
               for c, img in zip(cameras, images)) / len(cameras)


def main() -> None:
    torch.set_grad_enabled(False)
    for run in map(Path, sys.argv[1:]):
        scene = load_scene(run / "data" / "scene.json")
        model = load_model(run / "train" / "model.safetensors")
        radius = torch.exp(model.log_scales).amax(-1)
        seen = sum(in_frustum(model.means, radius, c, 0.01).long() for c in scene.cameras("train"))
        splits = {s: (scene.cameras(s), scene.load_images(s)[0]) for s in ("val", "test")}
        cells = [f"{run.name} ({len(model)} primitives)"]
        for k in (0, 2, 3, 4, 6):
            kept = model.select(seen >= k)
            cells.append(f"K={k}: −{len(model) - len(kept)}, val {mean_psnr(kept, *splits['val'], scene.background):.2f}, "
                         f"test {mean_psnr(kept, *splits['test'], scene.background):.2f}")
        print(" | ".join(cells), flush=True)


if __name__ == "__main__":
    main()
