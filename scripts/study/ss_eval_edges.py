"""Val and test PSNR of a run's model rendered with n x n rays per pixel, as the mean of n x n renders
with sub-pixel shifted principal points (for neural primitives the same as render.supersample = n;
for Gaussians the 0.3 px² dilation stays at the pixel scale), for each n given (default 1 2 3):
how a model trained at one n looks at another.
    usage: OMP_NUM_THREADS=1 .venv/bin/python scripts/study/ss_eval_edges.py RUN [N...]"""
import sys

import torch
from pathlib import Path
from radfield.core.render.antialias import shifted
from radfield.model_file import load_model
from radfield.evaluation.metrics import psnr
from radfield.core.render.rasterize import render
from radfield.datasets.scene import load_scene
run = Path(sys.argv[1]); ns = [int(x) for x in sys.argv[2:]] or [1, 2, 3]
scene = load_scene(run / "data" / "scene.json")
model = load_model(run / "train" / "model.safetensors")
out = []
for split in ("val", "test"):
    cams = scene.cameras(split); imgs, _ = scene.load_images(split)
    for n in ns:
        offs = [((a + 0.5) / n - 0.5, (b + 0.5) / n - 0.5) for a in range(n) for b in range(n)]
        tot = 0.0
        with torch.no_grad():
            for c, im in zip(cams, imgs):
                col = sum(render(model, shifted(c, o), background=scene.background).color for o in offs) / len(offs)
                tot += float(psnr(col.clamp(0, 1), im))
        out.append(f"{split} n={n}: {tot / len(cams):.2f}")
print(run.name, " | ".join(out))
