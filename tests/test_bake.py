"""Baking: the coverage of each primitive against a forward-only reference, pruning of hidden and
out-of-view primitives, float16 model files, the bake command and stage figures."""

from __future__ import annotations

import json
import math

import pytest
import torch

from radfield.delivery.bake import coverage, prune, to_fp16_and_back
from radfield.core.geometry.cameras import Camera, look_at
from radfield.errors import RadfieldError
from radfield.model_file import load_model, read_metadata, save_model
from radfield.core.kinds import Gaussians, random_neural
from radfield.core.render.rasterize import render
from radfield.core.splat.sh import C0, rgb_to_sh_dc

SIZE = 20
HIDDEN, OUTSIDE, VISIBLE = 3, 4, 5  # indices in `scene()`


def cameras() -> list[Camera]:
    eyes = [(0.0, -4.0, 0.0), (0.4, -4.0, 0.2), (-0.3, -4.0, -0.3)]
    return [Camera(fx=25, fy=25, cx=SIZE / 2, cy=SIZE / 2, width=SIZE, height=SIZE, c2w=look_at(eye, (0, 0, 0)))
            for eye in eyes]


def scene() -> Gaussians:
    """Three opaque walls at y = −1 (0, 1, 2), a primitive behind them (3), one behind every camera
    (4) and one in front of the walls (5)."""
    means = torch.tensor([[0, -1.0, 0], [0, -0.9, 0], [0, -0.8, 0], [0, 1.0, 0], [0, -8.0, 0], [0.2, -2.0, 0.1]])
    scales = torch.tensor([[4, 0.05, 4]] * 3 + [[0.2, 0.2, 0.2]] * 3)
    opacity = torch.tensor([0.995] * 3 + [0.9] * 3)
    rgb = torch.tensor([[0.5, 0.5, 0.5]] * 3 + [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    return Gaussians(means=means.double(), log_scales=scales.log().double(),
                     quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(6, 1).double(),
                     sh=rgb_to_sh_dc(rgb)[:, None, :].double(), opacities=torch.logit(opacity).double())


def reference_coverage(prims, cams) -> torch.Tensor:
    """max over views of Σ_p T α by forward renders only: primitive i white, all others black, on
    black (one render per primitive and view)."""
    out = torch.zeros(len(prims), dtype=torch.float64)
    for i in range(len(prims)):
        sh = torch.full_like(prims.sh[:, :1], -0.5 / C0)   # colour 0
        sh[i] = 0.5 / C0                                    # colour 1
        solo = Gaussians(means=prims.means, log_scales=prims.log_scales, quats=prims.quats, sh=sh,
                         opacities=prims.opacities)
        for camera in cams:
            image = render(solo, camera, background=(0.0, 0.0, 0.0)).color
            out[i] = max(out[i], float(image[..., 0].sum()))
    return out


def test_coverage_equals_the_forward_reference_and_prunes_hidden_and_outside():
    prims, cams = scene(), cameras()
    weights = coverage(prims, cams)
    torch.testing.assert_close(weights, reference_coverage(prims, cams), atol=1e-9, rtol=1e-9)
    assert weights[HIDDEN] < 1e-3 and weights[OUTSIDE] == 0      # behind the walls; behind every camera
    assert weights[VISIBLE] > 1.0 and weights[0] > 100 and (weights[1:3] > 0.1).all()  # the deeper walls show less
    baked, keep = prune(prims, weights)
    assert keep.tolist() == [True, True, True, False, False, True] and len(baked) == 4
    # the pruned primitives made no visible difference in any training view
    for camera in cams:
        assert (render(baked, camera).color - render(prims, camera).color).abs().max() < 2 / 255


def test_coverage_of_neural_primitives_matches_the_reference():
    prims = random_neural(12, extent=0.6, scale=0.3, b2=2.0, seed=4).to(dtype=torch.float64)
    cams = cameras()[:2]
    weights = coverage(prims, cams)
    reference = torch.zeros(len(prims), dtype=torch.float64)
    for i in range(len(prims)):
        sh = torch.full_like(prims.sh[:, :1], -0.5 / C0)
        sh[i] = 0.5 / C0
        for camera in cams:
            image = render(type(prims)(**{**prims.tensors(), "sh": sh}, omega0=prims.omega0), camera,
                           background=(0.0, 0.0, 0.0)).color
            reference[i] = max(reference[i], float(image[..., 0].sum()))
    torch.testing.assert_close(weights, reference, atol=1e-8, rtol=1e-8)


def test_fp16_model_files_round_trip(tmp_path):
    prims = random_neural(50, sh_degree=1, seed=1)
    full, half = tmp_path / "full.safetensors", tmp_path / "half.safetensors"
    save_model(full, prims)
    save_model(half, prims, extra={"baked": {"fp16": True}}, dtype=torch.float16)
    back = load_model(half)
    assert all(t.dtype == torch.float32 for t in back.tensors().values())
    for name, t in to_fp16_and_back(prims).tensors().items():
        assert torch.equal(getattr(back, name), t), name
        assert (getattr(back, name) - getattr(prims, name)).abs().max() <= 1e-3 * max(1.0, float(t.abs().max()))
    assert back.omega0 == prims.omega0 and json.loads(read_metadata(half)["baked"]) == {"fp16": True}
    assert half.stat().st_size < 0.55 * full.stat().st_size
    big = random_neural(2, seed=0)
    big.means[0, 0] = 1e6  # beyond float16
    with pytest.raises(RadfieldError, match="float16 range"):
        save_model(tmp_path / "big.safetensors", big, dtype=torch.float16)
    assert not (tmp_path / "big.safetensors").exists()


def test_bake_command_prunes_reports_and_keeps_psnr(tmp_path, cli):
    from radfield.demo.static import generate_scene

    data = generate_scene("blobs", tmp_path / "blobs", n_train=4, n_test=2, size=20)
    visible = random_neural(40, extent=0.5, scale=0.25, b2=1.0, seed=0)
    far = random_neural(5, extent=0.1, scale=0.05, seed=1)
    far.means += torch.tensor([200.0, 0.0, 0.0])  # outside every view
    model = type(visible)(**{k: torch.cat([getattr(visible, k), getattr(far, k)]) for k in visible.tensors()})
    save_model(tmp_path / "model.safetensors", model)
    code, out, err = cli("bake", tmp_path / "model.safetensors", "-d", data, "-o", tmp_path / "baked.safetensors",
                         "--fp16", "-q")
    assert code == 0, err
    baked = load_model(tmp_path / "baked.safetensors")
    recipe = json.loads(read_metadata(tmp_path / "baked.safetensors")["baked"])
    assert recipe["primitives_before"] == 45 and recipe["primitives_after"] == len(baked) <= 40
    assert recipe["fp16"] is True and math.isclose(recipe["min_weight"], 0.00392)
    assert "45 -> " in out and "PSNR" in out
    change = float(out.split("(")[-1].split(")")[0])
    assert abs(change) < 0.1
    code, _, err = cli("bake", tmp_path / "model.safetensors", "-d", data, "-o", tmp_path / "model.safetensors")
    assert code == 1 and "overwrite" in err


def test_bake_scores_the_valid_pixels_of_undistorted_photos(tmp_path):
    """Undistorting photos leaves an invalid (black) border; bake's before/after PSNR is over the
    valid pixels, the figure training and eval report (it was over the border too: fox at 540×960
    said 22.4 dB where eval said 29.8)."""
    import numpy as np

    from radfield.core.trainer.loop import mean_psnr
    from radfield.datasets.images import write_image
    from radfield.datasets.scene import read_dataset, scene_from_json
    from radfield.pipeline.config import load_defaults
    from radfield.stages.bake import bake_model

    w, h, f = 40, 30, 36.0
    (tmp_path / "images").mkdir()
    frames = []
    for i in range(3):   # frame 0 is the test view (every 8th)
        write_image(tmp_path / "images" / f"{i}.png", np.full((h, w, 3), 0.6, np.float32), bits=8)
        c2w = np.eye(4)
        c2w[:3, 3] = (0.3 * i, 0.0, 4.0)   # OpenGL axes: looking down −z at the origin
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": c2w.tolist()})
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"fl_x": f, "fl_y": f, "cx": w / 2, "cy": h / 2, "w": w, "h": h, "k1": 0.4, "k2": 0.1, "frames": frames}))
    content, _ = read_dataset(tmp_path, load_defaults()["data"])
    scene = scene_from_json(content, tmp_path / "scene.json")
    masks = scene.valid_masks("test")
    assert masks is not None and 0 < int((~masks).sum()) < masks.numel() // 2   # a border, not the whole view
    model = random_neural(30, extent=0.4, scale=0.3, seed=0)
    save_model(tmp_path / "model.safetensors", model)
    figures = bake_model(tmp_path / "model.safetensors", scene, tmp_path / "baked.safetensors", min_weight=0.0,
                         fp16=False, split="test")
    model = load_model(tmp_path / "model.safetensors")
    images = scene.load_images("test")[0]
    on_valid = mean_psnr(model, scene.cameras("test"), images, background=scene.background, masks=masks)
    everywhere = mean_psnr(model, scene.cameras("test"), images, background=scene.background)
    assert abs(on_valid - everywhere) > 1.0
    assert math.isclose(figures["psnr_before"], on_valid, abs_tol=1e-6)
