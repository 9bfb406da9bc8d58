"""CUDA smoke test: a tiny scene reconstructed end to end on the GPU (train, resume by continuing,
eval, render), and CUDA renders of the trained model compared with CPU renders of the same model.
Runs wherever torch sees a GPU; skipped elsewhere (CI machines without a GPU cannot run it).
`--no-cage` and no mesh.ply: a GPU machine need not have the geometry libraries (scripts/gpu_check.sh)."""

import json
import math

import numpy as np
import pytest
import torch

from radfield.model_file import load_model
from radfield.core.render.rasterize import render
from radfield.datasets.images import read_image
from radfield.demo.static import generate_scene
from radfield.datasets.scene import load_scene

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="torch sees no CUDA device")


def reconstruct_eval_render(cli, tmp_path, device: str) -> None:
    """The whole CLI path on `device`, checked against the CPU where the result must match."""
    scene_dir = generate_scene("blobs", tmp_path / "blobs", n_train=6, n_test=2, size=24, mesh=False)
    run_dir = tmp_path / "run"
    args = ["reconstruct", scene_dir, "-o", run_dir, "-q", "--device", device, "--no-cage", "--set", "init.num_points=200",
            "--set", "train.checkpoint_every=10", "--set", "train.eval_every=10"]
    code, out, err = cli(*args, "--iterations", "20")
    assert code == 0, err
    code, out, err = cli(*args, "--iterations", "25")  # continues from the final state on the device
    assert code == 0, err
    info = json.loads(cli("info", run_dir, "--json")[1])
    assert info["stages"]["train"]["continued_from"] == 20 and info["stages"]["train"]["iterations"] == 25
    assert math.isfinite(info["stages"]["eval"]["psnr"]) and info["pending_checkpoint"] is None

    code, out, err = cli("eval", run_dir, "-o", tmp_path / "report", "-q", "--device", device)
    assert code == 0, err
    report = json.loads((tmp_path / "report" / "metrics.json").read_text())
    assert report["psnr"] == pytest.approx(info["stages"]["eval"]["psnr"], abs=0.05)

    frames = {}
    for where in dict.fromkeys((device, "cpu")):   # once on the CPU itself
        code, out, err = cli("render", run_dir, "-o", tmp_path / f"frames-{where}", "-q", "--device", where)
        assert code == 0, err
        frames[where] = {p.name: read_image(p) for p in sorted((tmp_path / f"frames-{where}").iterdir())}
    assert frames[device].keys() == frames["cpu"].keys() and len(frames["cpu"]) == 2
    for name, image in frames["cpu"].items():
        assert np.abs(frames[device][name] - image).max() <= 2 / 255, name  # 8-bit PNGs: a rounding step

    # the float renders themselves agree closely
    model = load_model(run_dir / "train" / "model.safetensors")
    scene = load_scene(run_dir / "data" / "scene.json")
    for camera in scene.test_cameras:
        with torch.no_grad():
            on_cpu = render(model, camera, background=scene.background).color
            on_device = render(model.to(device), camera, background=scene.background).color.cpu()
        torch.testing.assert_close(on_device, on_cpu, atol=2e-4, rtol=0)


@needs_cuda
def test_cuda_reconstruct_eval_render_match_the_cpu(cli, tmp_path):
    reconstruct_eval_render(cli, tmp_path, "cuda")


def test_the_same_path_on_the_cpu(cli, tmp_path):
    """The smoke test's own body on the CPU, so CI runs every line of it (CUDA compared with itself there)."""
    reconstruct_eval_render(cli, tmp_path, "cpu")


@needs_cuda
@pytest.mark.parametrize("kind", ["neural", "gaussian"])
def test_cuda_training_steps_between_reads_do_not_synchronise(monkeypatch, kind):
    """torch.cuda.set_sync_debug_mode("error") over every step that does not read the step records
    (train.log_every 5; the strategy gathers its statistics every step but refines never, as
    refinement reads anyway; the rules refresh at multiples of 5): the Triton renderer, loss,
    D-SSIM, PSNR sums, Adam, the SH schedule, the frequency cap, σ ≥ 0, the footprint floor, ray
    jitter and random backgrounds run without waiting for the GPU, the binning's pair count
    (binning.pair_count, one read a view) excepted. Also the blocking copies to the device, which the
    CPU check of the same loop (tests/test_triton.py) cannot see."""
    from radfield.core.backends.gpu import binning
    from radfield.core.geometry.cameras import Camera, look_at
    from radfield.core.kinds import random_gaussians, random_neural
    from radfield.core.trainer import loop
    from radfield.pipeline.config import load_defaults

    cameras = [Camera(fx=20.8, fy=20.8, cx=8, cy=8, width=16, height=16, name=f"v{i}",
                      c2w=look_at((3 * math.cos(i), 3 * math.sin(i), 0.5), (0, 0, 0))) for i in range(3)]
    with torch.no_grad():
        images = torch.stack([render(random_neural(30, seed=1), c, background=(1.0, 1.0, 1.0)).color.clamp(0, 1)
                              for c in cameras])
    cfg = load_defaults()["train"]
    cfg.update(iterations=12, batch_views=2, log_every=5, checkpoint_every=5, eval_every=0, nonnegative_density=180.0,
               min_footprint=0.5, ray_jitter=0.5, random_background=True)
    cfg["densify"].update(start=1, stop=100, every=100)   # gathers every step, refines never
    reads = {5, 10, 12}   # the steps whose records are read
    decayed, count_pairs = loop.decayed, binning.pair_count
    counted = []

    def step_marker(lr, ratio, step, iterations):   # the first thing each step does
        torch.cuda.set_sync_debug_mode("default" if step + 1 in reads else "error")
        return decayed(lr, ratio, step, iterations)

    def allowed_read(touched):
        mode = torch.cuda.get_sync_debug_mode()
        torch.cuda.set_sync_debug_mode("default")
        try:
            counted.append(touched.device.type)
            return count_pairs(touched)
        finally:
            torch.cuda.set_sync_debug_mode(mode)

    monkeypatch.setattr(loop, "decayed", step_marker)
    monkeypatch.setattr(binning, "pair_count", allowed_read)
    log = []
    make = random_neural if kind == "neural" else random_gaussians
    try:
        loop.train(make(20, seed=2), cameras, images, cfg, background=(1.0, 1.0, 1.0), extent=1.0,
                      seed=0, device="cuda", alphas=torch.ones(3, 16, 16), on_step=lambda s, i: log.append((s, i)))
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert [s for s, _ in log] == list(range(1, 13)) and all(math.isfinite(i["loss"]) for _, i in log)
    assert counted == ["cuda"] * 24   # the Triton renderer drew every view (12 steps of 2)


@needs_cuda
def test_bench_render_profile_shows_where_the_gpu_time_goes(cli):
    code, out, err = cli("bench-render", "--primitives", "300", "--width", "64", "--height", "64", "--views", "1",
                         "--repeats", "1", "--device", "cuda", "--profile")
    assert code == 0, err
    for kind in ("neural", "neural-hard", "gaussian"):
        assert f"top costs, {kind}, one forward+backward, by device time" in out
        launches = [line for line in out.splitlines() if line.startswith(f"  kernel launches, {kind},")]
        assert len(launches) == 1 and int(launches[0].split()[-1]) > 0, out
