"""Which primitives make a view's worst pixels: render the view of split SPLIT (default val) with
the run's trained model, find the 5×5 window of largest squared error, drop each primitive that
projects near it (one at a time) and rank them by how much the error of the 7×7 pixels around it
falls; print the top ones (depth, projected radius, b2, ‖W2‖₁) and, for each, the training views
whose frustum holds it and how far it is from the nearest training camera.
    usage: .venv/bin/python scripts/study/worst_pixels.py RUN VIEW [SPLIT]"""
import sys
from pathlib import Path

import torch

from radfield.core.render.antialias import render_model
from radfield.model_file import load_model
from radfield.evaluation.metrics import psnr
from radfield.core.train.strategy import in_frustum
from radfield.datasets.scene import load_scene


def camera_space(means: torch.Tensor, camera) -> torch.Tensor:
    w2c = camera.w2c.to(means)
    return means @ w2c[:3, :3].T + w2c[:3, 3]


def main() -> None:
    run, view = Path(sys.argv[1]), sys.argv[2]
    split = sys.argv[3] if len(sys.argv) > 3 else "val"
    torch.set_grad_enabled(False)
    scene = load_scene(run / "data" / "scene.json")
    model = load_model(run / "train" / "model.safetensors")
    cameras, images = scene.cameras(split), scene.load_images(split)[0]
    k = [c.name for c in cameras].index(view)
    camera, truth = cameras[k], images[k]
    draw = lambda prims: render_model(prims, camera, background=scene.background).color  # noqa: E731
    base = draw(model)
    error = ((base - truth) ** 2).mean(-1)
    v0, u0 = divmod(int(torch.nn.functional.avg_pool2d(error[None, None], 5, 1, 2).argmax()), error.shape[1])
    window = (slice(max(v0 - 3, 0), v0 + 4), slice(max(u0 - 3, 0), u0 + 4))
    window_error = lambda img: float(((img - truth) ** 2).mean(-1)[window].mean())  # noqa: E731
    view_psnr = lambda img: float(psnr(img.clamp(0, 1), truth))  # noqa: E731
    p = camera_space(model.means, camera)
    u, v = camera.fx * p[:, 0] / p[:, 2] + camera.cx, camera.fy * p[:, 1] / p[:, 2] + camera.cy
    max_scale = torch.exp(model.log_scales).amax(-1)
    radius_px = camera.fx * max_scale / p[:, 2].clamp_min(1e-6)
    near = (p[:, 2] > 0) & ((u - u0) ** 2 + (v - v0) ** 2 < (8 + radius_px) ** 2)
    ranked = []
    for i in torch.nonzero(near).squeeze(1).tolist():
        keep = torch.ones(len(model), dtype=torch.bool)
        keep[i] = False
        ranked.append((window_error(base) - window_error(draw(model.select(keep))), i))
    ranked.sort(reverse=True)
    print(f"{split} view {view}: {view_psnr(base):.2f} dB; worst pixels around (v, u) = ({v0}, {u0}), "
          f"error {window_error(base):.2e}; {len(ranked)} primitives project near them")
    train = scene.cameras("train")
    for drop, i in ranked[:8]:
        seen = [c.name for c in train if bool(in_frustum(model.means[i:i + 1], max_scale[i:i + 1], c, 0.01))]
        nearest = min(float((model.means[i] - c.c2w[:3, 3].to(model.means)).norm()) for c in train)
        line = (f"primitive {i}: error −{drop:.2e}, depth {float(p[i, 2]):.3f}, radius {float(radius_px[i]):.1f} px")
        if model.kind == "neural":
            line += f", b2 {float(model.b2[i]):.3f}, ‖W2‖₁ {float(model.w2[i].abs().sum()):.3f}"
        print(f"{line}; in {len(seen)} training frusta ({', '.join(seen[:5])}{', …' if len(seen) > 5 else ''}), "
              f"{nearest:.3f} from the nearest training camera")
    keep = torch.ones(len(model), dtype=torch.bool)
    keep[[i for _, i in ranked[:5]]] = False
    print(f"without the top 5: the view {view_psnr(draw(model.select(keep))):.2f} dB")


if __name__ == "__main__":
    main()
