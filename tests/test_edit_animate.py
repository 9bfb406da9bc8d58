"""Animation and simulation: the XPBD soft body falls, stops at the ground with bounded energy;
`radfield animate` renders cage sequences to PNG + MP4; `radfield render` camera paths."""

from __future__ import annotations

import json

import imageio
import numpy as np
import pytest
import torch

from radfield.core.cage import tet_volumes, write_binding, write_cage
from radfield.core.camera_path import orbit, orbit_from_cameras, read_nerfstudio_path
from radfield.core.cameras import Camera, look_at, opencv_to_opengl
from radfield.core.errors import RadfieldError
from radfield.core.io import save_model
from radfield.core.primitives import random_neural
from radfield.datasets.images import read_image
from radfield.datasets.synthetic import generate_scene
from radfield.edit.field import box_cage
from radfield.edit.simulate import SoftBody, parse_simulation, simulate_cage


def test_soft_body_falls_stops_at_the_ground_with_bounded_energy():
    v, t = box_cage([-0.2, -0.2, 0.0], [0.2, 0.2, 0.4], 1)
    params = parse_simulation({"ground": -0.3, "frames": 40, "youngs_modulus": 5e5, "damping": 2.0, "substeps": 8})
    poses, figures = simulate_cage(v, t, params)
    heights = np.array([p[:, 2].mean() for p in poses])
    assert heights[10] < heights[0] - 0.05                       # it falls
    assert figures["min_height"] >= -0.3 - 1e-9                   # never through the ground
    assert poses[-1][:, 2].min() < -0.29                          # it landed
    assert figures["energy_max"] <= figures["energy_start"] * (1 + 1e-6)
    assert figures["energy_end"] < 0.6 * figures["energy_start"]  # the impact dissipated energy
    assert (tet_volumes(poses[-1], t) > 0).all()
    # at rest on the ground: the last frames barely move
    assert np.abs(poses[-1] - poses[-2]).max() < 0.01 < np.abs(poses[8] - poses[7]).max()
    # a free body with no ground contact keeps its shape (elastic forces vanish at rest)
    body = SoftBody(v, t, parse_simulation({"ground": -100.0, "substeps": 5}))
    body.step(1 / 30)
    drop = body.x - v
    assert np.allclose(drop, drop.mean(0), atol=1e-9) and drop[:, 2].mean() < 0


def test_simulation_parameters_are_checked():
    with pytest.raises(RadfieldError, match="simulate: unknown parameters \\['gravty'\\]"):
        parse_simulation({"gravty": [0, 0, -1]})
    with pytest.raises(RadfieldError, match="simulate.poisson_ratio"):
        parse_simulation({"poisson_ratio": 0.5})
    with pytest.raises(RadfieldError, match="simulate.frames"):
        parse_simulation({"frames": 0})


def test_orbit_and_nerfstudio_path(tmp_path):
    template = Camera(20.0, 20.0, 16.0, 16.0, 32, 32, look_at([3, 0, 1], [0, 0, 0]))
    cams = orbit([0.5, 0, 0], 2.0, 30.0, 8, template)
    for cam in cams:
        centre = cam.c2w[:3, 3].numpy()
        assert np.isclose(np.linalg.norm(centre - [0.5, 0, 0]), 2.0)
        assert np.isclose(np.degrees(np.arcsin((centre[2]) / 2.0)), 30.0)
        # the optical axis points at the target
        assert np.allclose(cam.c2w[:3, 2].numpy(), ([0.5, 0, 0] - centre) / 2.0)
    params = orbit_from_cameras(cams)
    assert np.allclose(params["target"], [0.5, 0, 0], atol=1e-9) and np.isclose(params["radius"], 2.0)
    assert np.allclose(params["up"], [0, 0, 1], atol=1e-9)
    path = tmp_path / "path.json"
    path.write_text(json.dumps({"render_width": 32, "render_height": 24, "fps": 12, "camera_path": [
        {"camera_to_world": opencv_to_opengl(c.c2w).flatten().tolist(), "fov": 60.0, "aspect": 32 / 24} for c in cams[:3]]}))
    read, fps = read_nerfstudio_path(path)
    assert fps == 12 and len(read) == 3 and read[0].height == 24
    assert torch.allclose(read[1].c2w, cams[1].c2w)
    assert np.isclose(read[0].fy, 12 / np.tan(np.radians(30)))
    path.write_text("{}")
    with pytest.raises(RadfieldError, match="not a nerfstudio camera path"):
        read_nerfstudio_path(path)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("anim")
    data = root / "data"
    generate_scene("blobs", data, n_train=3, n_test=2, size=32, seed=0)
    run = root / "run"
    (run / "train").mkdir(parents=True)
    (run / "tetra").mkdir()
    prims = random_neural(30, sh_degree=1, extent=0.4, scale=0.15, seed=4)
    save_model(run / "train" / "model.safetensors", prims)
    v, t = box_cage([-0.7, -0.7, -0.7], [0.7, 0.7, 0.7], 2)
    write_cage(run / "tetra", v, t)
    write_binding(run / "train" / "model_binding.npz", prims.means.numpy(), run / "tetra" / "cage.npz")
    (run / "radfield-run.json").write_text(json.dumps({"kind": "radfield-run", "input": str(data)}))
    return run, data, v, t


def test_animate_a_cage_sequence_to_png_and_mp4(cli, run, tmp_path):
    run_dir, data, v, t = run
    frames_dir = tmp_path / "cages"
    for i, angle in enumerate(np.linspace(0, 30, 4)):
        a = np.radians(angle) * (v[:, 2] + 0.7)
        c, s = np.cos(a), np.sin(a)
        write_cage(frames_dir / f"pose_{i}", np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]], 1), t)
    out = tmp_path / "anim"
    code, stdout, err = cli("animate", run_dir, "--cages", str(frames_dir / "pose_*" / "cage.vtk"), "-o", out, "-q", "--fps", "10")
    assert code == 0, err
    pngs = sorted(out.glob("frame_*.png"))
    assert len(pngs) == 4
    summary = json.loads((out / "animation.json").read_text())
    assert summary["frames"] == 4 and summary["consecutive_psnr"] > 15
    reader = imageio.get_reader(out / "animation.mp4", "ffmpeg")
    video = [frame for frame in reader]
    reader.close()
    assert len(video) == 4 and video[0].shape == (32, 32, 3)
    first = read_image(pngs[0])[..., :3]
    assert np.abs(video[0] / 255.0 - first).mean() < 0.03       # the video holds the frames (lossy)
    assert np.abs(read_image(pngs[0]) - read_image(pngs[-1])).max() > 0.05   # the twist shows

    # a wrong topology is a one-line error and leaves nothing
    other_v, other_t = box_cage([-1, -1, -1], [1, 1, 1], 1)
    write_cage(tmp_path / "bad", other_v, other_t)
    code, _, err = cli("animate", run_dir, "--cages", str(tmp_path / "bad"), "-o", tmp_path / "anim2")
    assert code == 1 and "another topology" in err and err.count("\n") == 1
    assert not (tmp_path / "anim2").exists()


def test_animate_a_simulation(cli, run, tmp_path):
    run_dir, data, v, t = run
    spec = tmp_path / "sim.yaml"
    spec.write_text("simulate: {gravity: [0, 0, -9.8], ground: -0.8, frames: 5, fps: 10, substeps: 10}\n")
    out = tmp_path / "sim"
    code, stdout, err = cli("animate", run_dir, "--simulate", spec, "-o", out, "-q", "--orbit")
    assert code == 0, err
    assert len(list(out.glob("frame_*.png"))) == 5 and (out / "animation.mp4").is_file()
    assert len(list((out / "cages").glob("frame_*/cage.vtk"))) == 5
    summary = json.loads((out / "animation.json").read_text())
    assert summary["simulation"]["min_height"] >= -0.8 - 1e-9


def test_render_orbit_and_camera_path_with_video(cli, run, tmp_path):
    run_dir, data, v, t = run
    code, stdout, err = cli("render", run_dir, "-d", data, "-o", tmp_path / "orbit", "--orbit", "3", "--video", tmp_path / "o.mp4", "-q")
    assert code == 0, err
    assert len(list((tmp_path / "orbit").glob("orbit_*.png"))) == 3
    reader = imageio.get_reader(tmp_path / "o.mp4", "ffmpeg")
    assert len([f for f in reader]) == 3
    reader.close()
    cams = orbit([0, 0, 0], 3.0, 10.0, 2, Camera(30.0, 30.0, 15.0, 10.0, 30, 20, torch.eye(4, dtype=torch.float64)))
    path = tmp_path / "p.json"
    path.write_text(json.dumps({"render_width": 30, "render_height": 20, "camera_path": [
        {"camera_to_world": opencv_to_opengl(c.c2w).flatten().tolist(), "fov": 50.0} for c in cams]}))
    code, _, err = cli("render", run_dir, "-d", data, "-o", tmp_path / "path", "--camera-path", path, "-q")
    assert code == 0, err
    images = sorted((tmp_path / "path").glob("path_*.png"))
    assert len(images) == 2 and read_image(images[0]).shape[:2] == (20, 30)
    code, _, err = cli("render", run_dir, "-d", data, "-o", tmp_path / "x", "--camera-path", path, "--orbit", "3")
    assert code == 1 and "exclude each other" in err
