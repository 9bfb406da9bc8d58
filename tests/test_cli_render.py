"""`radfield render` end to end, checked against an independent ray marcher written here in numpy
(it shares no code with radfield: it reads the model file itself and marches the summed density)."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from safetensors import safe_open

from radfield.core.geometry.cameras import look_at, opencv_to_opengl
from radfield.model_file import save_model
from radfield.core.kinds import NeuralPrimitives, siren_mlp_init
from radfield.datasets.images import read_image, write_image

SIZE = 40
ANGLE_X = 0.6


def radfield(*args, check=True):
    proc = subprocess.run([sys.executable, "-m", "radfield", *map(str, args)], capture_output=True, text=True, timeout=600)
    if check:
        assert proc.returncode == 0, proc.stderr
    return proc


def write_nerf_dataset(root, eyes):
    """A NeRF-synthetic test split: OpenGL camera-to-world matrices and (blank) images."""
    (root / "test").mkdir(parents=True)
    frames = []
    for i, eye in enumerate(eyes):
        c2w_gl = opencv_to_opengl(look_at(eye, (0, 0, 0)))
        frames.append({"file_path": f"./test/r_{i}", "transform_matrix": c2w_gl.tolist()})
        write_image(root / "test" / f"r_{i}.png", np.zeros((SIZE, SIZE, 3), np.float32))
    (root / "transforms_test.json").write_text(json.dumps({"camera_angle_x": ANGLE_X, "frames": frames}))


def separated_primitives(num, seed=0) -> NeuralPrimitives:
    """Random primitives that do not overlap (so splatting equals volume rendering), with a density
    that is positive everywhere (b2 > Σ|w2|) and SH degree 0."""
    g = torch.Generator().manual_seed(seed)
    means = []
    while len(means) < num:
        p = (torch.rand(3, generator=g) * 2 - 1) * 0.9
        if all((p - q).norm() > 0.5 for q in means):
            means.append(p)
    w1, b1, w2, _ = siren_mlp_init(num, generator=g)
    w2 = w2 * 30
    return NeuralPrimitives(
        means=torch.stack(means), log_scales=torch.log(0.1 + 0.12 * torch.rand(num, 3, generator=g)),
        quats=torch.randn(num, 4, generator=g), sh=torch.randn(num, 1, 3, generator=g) * 0.6,
        w1=w1, b1=b1, w2=w2, b2=w2.abs().sum(-1) + 0.5 + torch.rand(num, generator=g))


def ray_march(model_path, c2w_gl, near=0.01, far=7.0, steps=3000):
    """Classic emission-absorption volume rendering of the model's total density, in numpy."""
    with safe_open(str(model_path), framework="np") as f:
        t = {k: f.get_tensor(k).astype(np.float64) for k in f.keys()}
        omega0 = float(f.metadata()["omega0"])
    q = t["quats"] / np.linalg.norm(t["quats"], axis=1, keepdims=True)
    w, x, y, z = q.T
    rot = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                    2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                    2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)
    scales = np.exp(t["log_scales"])
    color = np.maximum(0.28209479177387814 * t["sh"][:, 0] + 0.5, 0.0)
    focal = 0.5 * SIZE / math.tan(0.5 * ANGLE_X)
    j, i = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5)
    d_cam = np.stack([(j - SIZE / 2) / focal, -(i - SIZE / 2) / focal, -np.ones_like(j)], -1)  # OpenGL camera
    d_world = (d_cam / np.linalg.norm(d_cam, axis=-1, keepdims=True)) @ np.asarray(c2w_gl)[:3, :3].T
    origin = np.asarray(c2w_gl)[:3, 3]
    dl = (far - near) / steps
    image, trans = np.zeros((SIZE, SIZE, 3)), np.ones((SIZE, SIZE))
    for l in near + dl * (np.arange(steps) + 0.5):
        pts = origin + l * d_world                                        # (H, W, 3)
        rel = pts[..., None, :] - t["means"]                              # (H, W, P, 3)
        local = np.einsum("pji,hwpj->hwpi", rot, rel) / scales            # ellipsoid frame
        inside = (local ** 2).sum(-1) <= 1.0
        u = rel / scales.max(-1)[:, None]
        hidden = np.cos(omega0 * (np.einsum("pnj,hwpj->hwpn", t["w1"], u) + t["b1"]))
        sigma = ((hidden * t["w2"]).sum(-1) + t["b2"]) / scales.max(-1) * inside  # world-unit density
        total = sigma.sum(-1)
        a = 1 - np.exp(-total * dl)
        image += (trans * a)[..., None] * (sigma @ color) / np.maximum(total, 1e-12)[..., None]
        trans *= 1 - a
    return image + trans[..., None]  # white background


def psnr(a, b):
    return -10 * math.log10(float(((a - b) ** 2).mean()))


def test_render_command_matches_independent_ray_marcher(tmp_path):
    prims = separated_primitives(6)
    save_model(tmp_path / "model.safetensors", prims)
    eyes = [(0.4, -3.2, 0.9), (-2.5, 1.8, -0.6)]
    write_nerf_dataset(tmp_path / "data", eyes)
    proc = radfield("render", tmp_path / "model.safetensors", "--dataset", tmp_path / "data", "-o", tmp_path / "out", "--quiet")
    assert "ms/frame" in proc.stdout
    for k, eye in enumerate(eyes):
        ours = read_image(tmp_path / "out" / f"r_{k}.png")[..., :3].astype(np.float64)
        marched = np.clip(ray_march(tmp_path / "model.safetensors", opencv_to_opengl(look_at(eye, (0, 0, 0)))), 0, 1)
        assert np.abs(marched - 1).max() > 0.3, "the marched view must show the primitives"
        assert psnr(ours, marched) > 40.0


@pytest.mark.parametrize("args, message", [
    (["render", "missing.safetensors", "--dataset", "data", "-o", "out"], "no such model file or run directory"),
    (["render", "model.safetensors", "--dataset", "nowhere", "-o", "out"], "dataset not found"),
    (["render", "model.safetensors", "--dataset", "data", "-o", "out", "--background", "1,1"], "--background must be three numbers"),
    (["render", "model.safetensors", "--dataset", "data", "-o", "out", "--split", "bogus"], "unknown split 'bogus'"),
    (["render", "model.safetensors", "--dataset", "data", "-o", "out", "--device", "tpu"], "--device must be cpu or cuda"),
    (["render", "data", "--dataset", "data", "-o", "out"], "has no trained model yet"),
    (["render", "garbage.safetensors", "--dataset", "data", "-o", "out"], "not a readable safetensors file"),
])
def test_render_user_errors_are_one_line(tmp_path, args, message):
    save_model(tmp_path / "model.safetensors", separated_primitives(2))
    (tmp_path / "garbage.safetensors").write_bytes(b"nope")
    write_nerf_dataset(tmp_path / "data", [(0, -3, 0)])
    proc = subprocess.run([sys.executable, "-m", "radfield", *args], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert proc.returncode == 1
    assert message in proc.stderr and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert not (tmp_path / "out").exists()


def test_version_and_help():
    assert radfield("--version").stdout.startswith("radfield ")
    for command in ([], ["render"], ["bench-render"]):
        assert "Usage" in radfield(*command, "--help").stdout
