"""Where a trained run's held-out error sits, for the capture study (issue 11): per-primitive
statistics and ablation renders of RUN's model on the test and val views.

Per primitive (world frame): size r = max(s) / extent, the nearest training camera's depth z_min
/ extent, how many training views see it (frustum test of its bounding sphere), its largest hidden
unit frequency k = ω0 max_n ‖W1_n‖ (rad per unit of u; neural only) and its largest projected
radius ρ_max (px). Ablations: PSNR after dropping the primitives of one class (the nearest 5 % by
z_min, the largest 5 % by r, those seen in fewer than 25 % of the training views): if dropping
raises a view's PSNR, those primitives hurt it (floaters). Error maps: PNG grids
photo | render | squared error ×10 per test view, and the share of squared error in the image's
border (outer 10 %) and on edges (photo gradient in the top 20 %).

    usage: .venv/bin/python scripts/study/capture_diag.py RUN [--out DIR]
"""
import argparse
import json
from pathlib import Path

import numpy as np
import torch

from radfield.core.train.frequency import footprint, view_stack
from radfield.model_file import load_model
from radfield.core.train.losses import psnr
from radfield.core.render.rasterize import render
from radfield.core.train.strategy import in_frustum
from radfield.datasets.images import write_image
from radfield.stages.data import load_scene


def split_psnr(model, cameras, images, masks, bg, near):
    out = []
    with torch.no_grad():
        for k, (cam, img) in enumerate(zip(cameras, images)):
            color = render(model, cam, background=bg, near=near).color.clamp(0, 1)
            out.append(float(psnr(color, img, None if masks is None else masks[k])))
    return float(np.mean(out)), out


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("run", type=Path)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    scene = load_scene(args.run / "data" / "scene.json")
    model = load_model(args.run / "train" / "model.safetensors")
    near = 0.01
    bg = scene.background
    extent = scene.extent
    train = scene.cameras("train")
    smax = torch.exp(model.log_scales.amax(-1))
    means = model.means
    w2c = torch.stack([c.w2c for c in train]).float()
    z = torch.einsum("cij,pj->cpi", w2c[:, :3, :3], means) + w2c[:, None, :3, 3]
    seen = torch.stack([in_frustum(means, smax, c, near) for c in train])
    zmin = torch.where(seen, z[..., 2], torch.inf).amin(0)
    nviews = seen.sum(0).float()
    rho = footprint(means, smax, view_stack(train), near)
    stats = {"primitives": len(model), "train_views": len(train),
             "r_median": float((smax / extent).median()), "r_p95": float((smax / extent).quantile(0.95)),
             "zmin_p05": float((zmin / extent).quantile(0.05)), "zmin_median": float((zmin / extent).median()),
             "views_median": float(nviews.median()), "views_lt25%": float((nviews < 0.25 * len(train)).float().mean()),
             "rho_median": float(rho.median())}
    if model.kind == "neural":
        k = model.omega0 * model.w1.norm(dim=-1).amax(-1)
        stats.update(k_median=float(k.median()), k_p95=float(k.quantile(0.95)),
                     k_gt_pi=float((k > np.pi).float().mean()), k_over_rho_median=float((k / rho.clamp_min(1e-6)).median()))
        # opacity-ish: peak density bound ‖W2‖₁ + b2 (paper eq. 6)
        stats["sigma_max_median"] = float((model.w2.abs().sum(-1) + model.b2).median())
    print(json.dumps(stats, indent=1))
    splits = {s: (scene.cameras(s), scene.load_images(s)[0], scene.valid_masks(s)) for s in ("test", "val") if s in scene.splits}
    classes = {"near 5%": zmin <= zmin.quantile(0.05), "large 5%": smax >= smax.quantile(0.95),
               "seen <25% views": nviews < 0.25 * len(train)}
    for s, (cams, imgs, masks) in splits.items():
        base, per = split_psnr(model, cams, imgs, masks, bg, near)
        row = [f"{s}: all {base:.2f} ({' '.join(f'{p:.1f}' for p in per)})"]
        for name, drop in classes.items():
            if int(drop.sum()) == 0:
                continue
            sub = model.map(lambda t, keep=~drop: t[keep] if t.ndim and t.shape[0] == len(model) else t)
            value, _ = split_psnr(sub, cams, imgs, masks, bg, near)
            row.append(f"−{name} ({int(drop.sum())}): {value:.2f}")
        print("  ".join(row))
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        cams, imgs, masks = splits["test"]
        border_share, edge_share = [], []
        for k, (cam, img) in enumerate(zip(cams, imgs)):
            with torch.no_grad():
                color = render(model, cam, background=bg, near=near).color.clamp(0, 1)
            err = ((color - img) ** 2).sum(-1)
            if masks is not None:
                err = err * masks[k]
            h, w = err.shape
            b = np.zeros((h, w), bool)
            bh, bw = max(h // 10, 1), max(w // 10, 1)
            b[:bh], b[-bh:], b[:, :bw], b[:, -bw:] = True, True, True, True
            gray = img.mean(-1).numpy()
            gy, gx = np.gradient(gray)
            g = np.hypot(gx, gy)
            edge = g >= np.quantile(g, 0.8)
            e = err.numpy()
            border_share.append(e[b].sum() / e.sum())
            edge_share.append(e[edge].sum() / e.sum())
            heat = np.repeat(np.clip(e * 10, 0, 1)[..., None], 3, -1)
            write_image(args.out / f"{cam.name}.png", np.concatenate([img.numpy(), color.numpy(), heat], 1))
        print(f"test error share: border 10% {np.mean(border_share):.2f} (pixels {b.mean():.2f}), "
              f"edges top 20% gradient {np.mean(edge_share):.2f}")


if __name__ == "__main__":
    main()
