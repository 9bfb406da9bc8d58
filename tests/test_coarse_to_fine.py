"""Coarse to fine (core/train/coarse_to_fine.py, train.coarse_levels): the schedule of downscale
factors, the downscaled views (area averages, cameras through the same rays, masks valid only where
every photo pixel is), and training that renders the smaller views early and reaches full size."""

import math

import numpy as np
import torch

from radfield.core.geometry.cameras import Camera, look_at
from radfield.core.kinds import random_neural
from radfield.core.render.rasterize import render
from radfield.core.train.coarse_to_fine import ViewPyramid, factor_at
from radfield.core.trainer.loop import mean_psnr, train

BG = (1.0, 1.0, 1.0)


def test_the_factor_halves_at_equal_intervals_and_is_one_from_until_on():
    factors = [factor_at(step, 100, 2, 0.5) for step in range(100)]
    assert factors == [4] * 25 + [2] * 25 + [1] * 50
    assert [factor_at(step, 90, 3, 0.4) for step in (0, 11, 12, 23, 24, 35, 36, 89)] == [8, 8, 4, 4, 2, 2, 1, 1]
    assert all(factor_at(step, 100, 0, 0.5) == 1 for step in range(100))


def test_the_pyramid_averages_the_photo_pixels_and_scales_the_cameras():
    g = torch.Generator().manual_seed(0)
    images = torch.rand(2, 12, 16, 3, generator=g)
    masks = torch.ones(2, 12, 16, dtype=torch.bool)
    masks[0, 0, 0] = False                            # one invalid photo pixel spoils its 2×2 block only
    camera = Camera(20.0, 20.0, 8.0, 6.0, 16, 12, look_at((0.0, -3.0, 0.0), (0.0, 0.0, 0.0)))
    pyramid = ViewPyramid([camera, camera], images, masks, None)
    cameras, small, valid, alphas = pyramid.at(2)
    assert small.shape == (2, 6, 8, 3) and valid.shape == (2, 6, 8) and alphas is None
    torch.testing.assert_close(small[1, 2, 3], images[1, 4:6, 6:8].mean((0, 1)))
    assert not valid[0, 0, 0] and int(valid.sum()) == 2 * 48 - 1
    assert (cameras[0].width, cameras[0].height, cameras[0].fx, cameras[0].cx) == (8, 6, 10.0, 4.0)
    assert pyramid.at(2)[1] is small and pyramid.at(1)[1] is images   # made once; full size as given


def views(size=24, n=4):
    truth = random_neural(24, seed=3)
    cams = [Camera(fx=1.2 * size, fy=1.2 * size, cx=size / 2, cy=size / 2, width=size, height=size,
                   c2w=look_at((3.0 * math.cos(a), 3.0 * math.sin(a), 0.8), (0.0, 0.0, 0.0)), name=f"c{k}")
            for k, a in enumerate(2 * math.pi * np.arange(n) / n)]
    with torch.no_grad():
        images = torch.stack([render(truth, cam, background=BG).color for cam in cams])
    return truth, cams, images


def test_training_renders_the_small_views_first_and_fits_the_full_size_ones(cfg, monkeypatch):
    import radfield.core.trainer.loop as loop

    truth, cams, images = views()
    start = random_neural(24, seed=4)
    seen, draw = [], loop.render_supersampled

    def recorded(prims, camera, *args, **kwargs):
        seen.append(camera.width)
        return draw(prims, camera, *args, **kwargs)

    monkeypatch.setattr(loop, "render_supersampled", recorded)
    train_cfg = cfg("train", iterations=60, sh_degree=0, checkpoint_every=1000, eval_every=0, coarse_levels=2,
                    coarse_until=0.5)
    train_cfg["lr"] = {k: v * 10 for k, v in train_cfg["lr"].items()}    # a short run: larger steps
    coarse = train(start, cams, images, train_cfg, background=BG, extent=1.0, seed=0).primitives()
    assert seen == [6] * 15 + [12] * 15 + [24] * 30
    full = train(start, cams, images, {**train_cfg, "coarse_levels": 0}, background=BG, extent=1.0, seed=0).primitives()
    assert seen[60:] == [24] * 60
    before, after, reference = (mean_psnr(prims, cams, images, background=BG) for prims in (start, coarse, full))
    # the coarse start fits the full-size views, nearly as well as training at full size throughout
    assert after > before + 1.5 and after > reference - 1.0, (before, after, reference)
