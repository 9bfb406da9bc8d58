"""Where the held-out error of a generated scene comes from: each test pixel's squared error (summed
over RGB, on the white background) split into silhouette / occlusion edges, specular highlights
and the rest, from the analytic scene (radfield.demo), with two reference errors:

- silhouette: some of the pixel's 8 x 8 regular sub-rays miss the scene and some hit it;
- occlusion edge: they all hit, but not all the same shape;
- highlight: neither, and the specular term averaged over the sub-rays exceeds TAU;
- rest: everything else (flat-shaded interiors, background).

`sampling floor` = the dataset's own pixels against the scene rendered with 16 x 16 regular rays
per pixel (nearly the pixel's exact area average, what one 3D scene gives consistently in every
view): the part of the pixels no view-consistent model can fit; `SH-3 fit` = at the centre point
of every test highlight pixel, the error of the degree-3 SH least-squares fit of its specular
radiance towards the training cameras that see it, predicted towards the test camera: how much of
a highlight one SH-3 colour per surface point cannot follow (not a strict floor: a model may also
change which primitives a ray sees from view to view). PSNR (all) pools the squared error of all
views (the eval stage averages per-view PSNRs, a few tenths of a dB higher).

    usage: .venv/bin/python scripts/study/error_shares.py DATASET RENDERS... [--val-every 10 (runs of the study protocol)]
    (RENDERS: folders of `radfield render RUN --split test` PNGs, one per run)
"""
import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

from radfield.core.splat.sh import sh_basis
from radfield.datasets.images import read_image
from radfield.demo.scenes import get_scene, orbit_cameras
from radfield.demo.raytrace import intersect, render_view, shade

TAU = 0.02  # specular level that counts as a highlight (about 5 of 255)


def sub_rays(camera, k):
    """Rays of a k x k regular grid in every pixel: directions (H*W*k*k, 3), origin (3,)."""
    g = (np.arange(k) + 0.5) / k
    off = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    i = np.arange(camera.height)[:, None, None] + off[None, None, :, 0]
    j = np.arange(camera.width)[None, :, None] + off[None, None, :, 1]
    i, j = np.broadcast_arrays(i, j)
    d = np.stack([(j - camera.cx) / camera.fx, (i - camera.cy) / camera.fy, np.ones_like(i)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    c2w = camera.c2w.numpy()
    return d.reshape(-1, 3) @ c2w[:3, :3].T, c2w[:3, 3]


def classify(scene, camera, k=8):
    d, o = sub_rays(camera, k)
    t, n, index = intersect(scene, o, d)
    _, spec = shade(scene, o, d, t, n, index)
    index, spec = index.reshape(camera.height, camera.width, -1), spec.reshape(camera.height, camera.width, -1)
    edge = (index != index[..., :1]).any(-1)
    silhouette = edge & (index < 0).any(-1)
    highlight = ~edge & (spec.mean(-1) > TAU)
    return np.select([silhouette, edge, highlight], [0, 1, 2], 3)


def sh3_floor(scene, camera, train_cams, mask):
    """Squared error (summed over RGB) of the SH-3 prediction of the specular term at the centre
    ray of each pixel in `mask` (see the module docstring)."""
    d, o = sub_rays(camera, 1)
    d = d[mask.ravel()]
    t, n, index = intersect(scene, o, d)
    x = o + t[:, None] * d
    light = np.asarray(scene.lighting.direction)
    eyes = np.stack([c.c2w.numpy()[:3, 3] for c in train_cams])
    err = np.zeros(len(d))
    for p in range(len(d)):
        material = scene.primitives[index[p]].material
        to_x = x[p] - eyes
        dist = np.linalg.norm(to_x, axis=1)
        dirs = to_x / dist[:, None]
        t_v, _, i_v = intersect(scene, eyes, dirs)  # origins per ray
        seen = (i_v == index[p]) & (np.abs(t_v - dist) < 1e-4) & (dirs @ n[p] < 0)

        def spec(v):  # v: ray directions towards the point
            h = light - v
            h /= np.linalg.norm(h, axis=-1, keepdims=True)
            return material.specular * np.clip(h @ n[p], 0, None) ** material.shininess * (n[p] @ light > 0)

        basis = sh_basis(torch.from_numpy(-dirs[seen]), 3).numpy()  # SH of the direction towards the eye
        if seen.sum() < 4:
            continue
        coef = np.linalg.solve(basis.T @ basis + 1e-3 * np.eye(16), basis.T @ spec(dirs[seen]))
        pred = sh_basis(torch.from_numpy(-d[p][None]), 3).numpy() @ coef
        err[p] = 3 * (pred[0] - spec(d[p][None])[0]) ** 2
    return err


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset", type=Path)
    ap.add_argument("renders", type=Path, nargs="*")
    ap.add_argument("--val-every", type=int, default=0, help="the runs' data.val_every (10 in the study protocol)")
    ap.add_argument("--no-sh", action="store_true")
    a = ap.parse_args()
    meta = json.loads((a.dataset / "scene.json").read_text())
    scene = get_scene(meta["name"])
    n_train = len(json.loads((a.dataset / "transforms_train.json").read_text())["frames"])
    n_test = len(json.loads((a.dataset / "transforms_test.json").read_text())["frames"])
    size = read_image(a.dataset / "test" / "r_0.png").shape[0]
    train, test = orbit_cameras(n_train, n_test, size, meta["seed"])
    fit_cams = [c for k, c in enumerate(train) if a.val_every == 0 or (k + 1) % a.val_every]
    names = ["silhouette", "occlusion edge", "highlight", "rest"]
    classes = range(len(names))
    se = {r: np.zeros(len(names)) for r in a.renders}
    floor, sh_floor, count = np.zeros(len(names)), 0.0, np.zeros(len(names))
    for camera in test:
        cls = classify(scene, camera)
        gt = read_image(a.dataset / "test" / f"{camera.name}.png")
        gt = gt[..., :3] + 1 - gt[..., 3:]
        exact = render_view(scene, camera, samples=16)[0]
        exact = exact[..., :3] + 1 - exact[..., 3:]
        for c in classes:
            count[c] += (cls == c).sum()
            floor[c] += ((gt - exact) ** 2).sum(-1)[cls == c].sum()
        for r in a.renders:
            err = ((read_image(r / f"{camera.name}.png")[..., :3] - gt) ** 2).sum(-1)
            for c in classes:
                se[r][c] += err[cls == c].sum()
        if not a.no_sh:
            sh_floor += sh3_floor(scene, camera, fit_cams, cls == 2).sum()
    pixels = count.sum()

    def psnr(total, n):
        return -10 * math.log10(total / (3 * n)) if total > 0 else float("inf")

    print(f"{a.dataset}: {len(test)} test views, {int(pixels)} pixels; classes from 8x8 sub-rays, highlight: "
          f"specular > {TAU}; share of the squared error (PSNR within the class)")
    print("| source | PSNR (all) | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    print("| pixels | | " + " | ".join(f"{count[c] / pixels:.1%}" for c in classes) + " |")

    def row(label, errors):
        tot = errors.sum()
        print(f"| {label} | {psnr(tot, pixels):.2f} | "
              + " | ".join(f"{errors[c] / tot:.1%} ({psnr(errors[c], count[c]):.2f})" for c in classes) + " |")

    for r in a.renders:
        row(r.parent.parent.name if r.name == "renders" else r.name, se[r])  # RUN/eval/renders: RUN
    row("sampling floor (dataset vs 16x16)", floor)
    if not a.no_sh:
        print(f"| SH-3 fit (highlights only) | {psnr(sh_floor, pixels):.2f} | | | "
              f"({psnr(sh_floor, count[2]):.2f}) | |")


if __name__ == "__main__":
    main()
