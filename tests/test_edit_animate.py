"""The XPBD soft body falls and stops at the ground with bounded energy; camera paths (orbit,
nerfstudio JSON). The animate and render commands are tested in test_edit_cli.py."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from radfield.core.geometry.cage import tet_volumes
from radfield.core.geometry.camera_path import orbit, orbit_from_cameras, read_nerfstudio_path
from radfield.core.geometry.cameras import Camera, look_at, opencv_to_opengl
from radfield.errors import RadfieldError
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
    # a ground above the cage's lowest point: the body would start inside it (its bottom tets flipped)
    v, t = box_cage([-0.2, -0.2, 0.0], [0.2, 0.2, 0.4], 1)
    with pytest.raises(RadfieldError, match=r"simulate.ground: 0.1 is above the cage's lowest point \(0 along"):
        simulate_cage(v, t, parse_simulation({"ground": 0.1}))
    # far too soft for its load: refused at the frame, once doubling the substeps cannot help
    with pytest.raises(RadfieldError, match="tets of the cage invert at frame 1 even with 5120 substeps"):
        simulate_cage(v, t, parse_simulation({"youngs_modulus": 1e-3, "gravity": [0, 0, -1e6], "ground": -0.01, "fps": 1}))


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


@pytest.mark.parametrize("text, value", [("1e6", 1e6), ("2e4", 2e4), ("1E6", 1e6), ("-1.5e-3", -1.5e-3),
                                         ("+3e2", 300.0), (".5e3", 500.0), ("1.e2", 100.0)])
def test_yaml_reads_numbers_as_users_write_them(tmp_path, text, value):
    """`youngs_modulus: 1e6` (the docs' own example) was the string '1e6' to YAML 1.1's loader."""
    from radfield.edit.animation_spec import read_animation
    from radfield.edit.simulate import read_simulation
    from radfield.util.yamlfile import parse_yaml

    assert parse_yaml(f"x: {text}") == {"x": value} and isinstance(parse_yaml(f"x: {text}")["x"], float)
    sim = tmp_path / "sim.yaml"
    sim.write_text(f"simulate: {{youngs_modulus: {text.lstrip('-')}, ground: {text}}}\n")
    params = read_simulation(sim)
    assert params["youngs_modulus"] == abs(value) and params["ground"] == value
    anim = tmp_path / "anim.yaml"
    anim.write_text(f"simulate: {{density: {text.lstrip('-')}}}\nanimate: {{elevation: {text}}}\n")
    assert read_animation(anim)["elevation"] == value
    # what is not a number stays a string (and is refused as one)
    sim.write_text("simulate: {youngs_modulus: 1e}\n")
    with pytest.raises(RadfieldError, match="youngs_modulus: expected a number, got '1e'"):
        read_simulation(sim)


def test_a_coarse_time_step_never_inverts_the_cage():
    """The docs' settings with fps 12 (h = 1/240 s at 20 substeps) inverted tets of the objects
    scene's cage at frame 3; here a cage with thin tets (a box of 5 × 5 × 5 cells, 0.4 wide)
    dropped onto the ground at 12 fps: the step is sub-divided until no tet inverts."""
    v, t = box_cage([-0.2, -0.2, 0.0], [0.2, 0.2, 0.4], 5)
    rest = tet_volumes(v, t)
    params = parse_simulation({"ground": -0.05, "youngs_modulus": 1e6, "frames": 12, "fps": 12, "substeps": 2,
                               "initial_velocity": [0.0, 0.0, -3.0]})
    lines = []
    poses, figures = simulate_cage(v, t, params, log=lines.append)
    assert len(poses) == 12
    # what is printed before the frames are rendered says what is being done, not "simulated N frames"
    assert lines[0].startswith("simulating 12 frames") and not any("simulated" in line for line in lines)
    for pose in poses:
        assert (tet_volumes(pose, t) > 1e-9 * rest).all()
    assert figures["substeps_max"] > 2 and figures["min_height"] >= -0.05 - 1e-9
