"""`radfield edit`: a new run directory that render/eval/info read unchanged; the spec's
operations; one-line errors that leave nothing behind. `radfield animate` (cage sequences and
simulations to PNG + MP4) and the camera paths of `radfield render`."""

from __future__ import annotations

import json

import imageio
import numpy as np
import pytest
import torch
import yaml

from radfield.core.geometry.cage import write_cage
from radfield.core.geometry.camera_path import orbit
from radfield.core.geometry.cameras import Camera, opencv_to_opengl
from radfield.model_file import load_model
from radfield.datasets.images import read_image
from radfield.datasets.readers import load_dataset
from radfield.edit.field import box_cage


@pytest.fixture(scope="module")
def scene(tmp_path_factory, hand_run):
    root = tmp_path_factory.mktemp("edit")
    data, run, v, t = hand_run(root)
    return root, run, data, v, t


def _spec(path, operations):
    path.write_text(yaml.safe_dump({"operations": operations}))
    return path


def test_edit_writes_a_run_that_render_eval_and_info_read(cli, scene, tmp_path):
    root, run, data, v, t = scene
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    spec = _spec(tmp_path / "edit.yaml", [
        {"transform": {"select": {"sphere": {"center": [0.8, 0.8, 0.8], "radius": 0.3}}, "translate": [0.1, 0, 0], "falloff": 0.2}},
        {"twist": {"axis": "z", "degrees_per_unit": 20, "origin": [0, 0, 0], "select": "all"}},
        {"bend": {"axis": "y", "degrees_per_unit": 15, "select": "all"}},
        {"taper": {"axis": "z", "factor": 0.2, "select": "all"}},
    ])
    out = tmp_path / "edited"
    code, stdout, err = cli("edit", run, "--spec", spec, "-o", out, "--rotate", "0,0,30", "-q")
    assert code == 0, err
    assert "wrote" in stdout
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before   # source untouched
    for name in ("model.safetensors", "cage.npz", "cage.vtk", "model_binding.npz", "spec.yaml", "manifest.json"):
        assert (out / "edit" / name).is_file(), name
    assert (out / "config.yaml").read_text() == (run / "config.yaml").read_text()
    assert len(yaml.safe_load((out / "edit" / "spec.yaml").read_text())["operations"]) == 5
    model = load_model(out / "edit" / "model.safetensors")
    assert not torch.equal(model.means, load_model(run / "train" / "model.safetensors").means)

    code, stdout, err = cli("info", out, "--json")
    assert code == 0, err
    info = json.loads(stdout)
    assert info["model"].endswith("edit/model.safetensors") and info["stages"]["edit"]["done"]
    assert info["input"] == str(data.resolve())
    code, stdout, err = cli("eval", out, "-o", tmp_path / "report", "-q")
    assert code == 0, err
    assert (tmp_path / "report" / "metrics.json").is_file()
    code, _, err = cli("render", out, "-d", data, "-o", tmp_path / "frames", "-q")
    assert code == 0, err
    assert len(list((tmp_path / "frames").glob("*.png"))) == 2
    # an edited run is a source too
    code, _, err = cli("edit", out, "-o", tmp_path / "again", "--translate", "0,0,0.1", "-q")
    assert code == 0, err


def test_identity_deform_keeps_the_model_file_content(cli, scene, tmp_path):
    root, run, data, v, t = scene
    spec = _spec(tmp_path / "same.yaml", [{"deform": {"cage": str(run / "tetra" / "cage.vtk")}}])
    code, _, err = cli("edit", run, "--spec", spec, "-o", tmp_path / "same", "-q")
    assert code == 0, err
    a, b = load_model(run / "train" / "model.safetensors"), load_model(tmp_path / "same" / "edit" / "model.safetensors")
    for name, value in a.tensors().items():
        assert torch.equal(value, b.tensors()[name]), name


def test_deform_from_a_moved_cage_file_and_a_model_without_cage(cli, scene, tmp_path):
    root, run, data, v, t = scene
    moved = v.copy()
    moved[:, 2] *= 1.3
    write_cage(tmp_path / "moved", moved, t)
    spec = _spec(tmp_path / "d.yaml", [{"deform": {"cage": "moved/cage.vtk"}}])   # relative to the spec
    code, _, err = cli("edit", run, "--spec", spec, "-o", tmp_path / "d", "-q")
    assert code == 0, err
    cage = np.load(tmp_path / "d" / "edit" / "cage.npz")
    assert np.allclose(cage["vertices"], moved)
    # a stretch is not a similarity: preserve_opacity is on by default, and --no-preserve-opacity turns it off
    assert load_model(tmp_path / "d" / "edit" / "model.safetensors").rest_metric is not None
    code, _, err = cli("edit", run, "--spec", spec, "-o", tmp_path / "n", "--no-preserve-opacity", "-q")
    assert code == 0, err
    assert load_model(tmp_path / "n" / "edit" / "model.safetensors").rest_metric is None
    # preserve_opacity: the optional rest_metric tensor, G = r² A⁻ᵀA⁻¹, survives the model file
    code, _, err = cli("edit", run, "--spec", spec, "-o", tmp_path / "p", "--preserve-opacity", "-q")
    assert code == 0, err
    kept = load_model(tmp_path / "p" / "edit" / "model.safetensors")
    assert kept.rest_metric is not None and kept.rest_metric.shape == (len(kept), 6)
    assert not torch.allclose(kept.rest_metric[:, 2], torch.ones(len(kept)))   # z stretched by 1.3
    code, _, err = cli("edit", tmp_path / "p", "-o", tmp_path / "p2", "--scale", "2", "-q")   # a similarity keeps G
    assert code == 0, err
    again = load_model(tmp_path / "p2" / "edit" / "model.safetensors")
    assert torch.allclose(again.rest_metric, kept.rest_metric, rtol=1e-4, atol=1e-6)
    # a model file without a cage: whole-field transforms map the primitives directly
    model = run / "train" / "model.safetensors"
    code, _, err = cli("edit", model, "-o", tmp_path / "m", "--scale", "2", "--translate", "1,0,0", "-q")
    assert code == 0, err
    a, b = load_model(model), load_model(tmp_path / "m" / "edit" / "model.safetensors")
    assert torch.allclose(b.means, 2 * a.means + torch.tensor([1.0, 0, 0]), atol=1e-6)
    assert torch.allclose(b.log_scales.sort(-1).values, (a.log_scales + np.log(2)).sort(-1).values, atol=1e-5)


@pytest.mark.parametrize("ops, message", [
    ([{"explode": {}}], "operations\\[0\\]: unknown operation 'explode'"),
    ([{"deform": {"cage": "other.npz"}}], "operations\\[0\\].deform.cage: .* has another topology"),
    ([{"transform": {"select": {"cube": {}}, "translate": [0, 0, 1]}}], "operations\\[0\\].transform.select: unknown selection 'cube'"),
    ([{"transform": {"select": {"sphere": {"center": [9, 9, 9], "radius": 0.1}}, "translate": [0, 0, 1]}}], "selects no cage vertex"),
    ([{"twist": {"axis": "z", "degrees_per_unit": "a lot"}}], "operations\\[0\\].twist.degrees_per_unit: expected a number"),
    ([{"transform": {"scale": 2, "shear": 1}}], "unknown arguments \\['shear'\\]"),
    ([{"transform": {"select": {"box": {"min": [-1, -1, 0.5], "max": [1, 1, 1]}}, "translate": [0, 0, -2]}}], "inverted tets in the deformed cage"),
])
def test_spec_errors_are_one_line_and_leave_nothing(cli, scene, tmp_path, ops, message):
    root, run, data, v, t = scene
    other_v, other_t = box_cage([-1, -1, -1], [1, 1, 1], 1)
    np.savez(tmp_path / "other.npz", vertices=other_v, tets=other_t)
    spec = _spec(tmp_path / "bad.yaml", ops)
    out = tmp_path / "out"
    code, stdout, err = cli("edit", run, "--spec", spec, "-o", out)
    assert code == 1
    assert err.startswith("radfield: error: ") and err.count("\n") == 1, err
    import re
    assert re.search(message, err), err
    assert err.startswith(f"radfield: error: {spec}: "), err   # every error of a spec names its file first
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.yaml", "other.npz"]


def test_a_yaml_mistake_in_any_file_says_where(cli, scene, tmp_path):
    """A syntax error in an edit spec, an animation spec or a pipeline config: the file, the line and
    the column, in one line."""
    root, run, data, v, t = scene
    bad = tmp_path / "bad.yaml"
    bad.write_text("operations:\n  - transform: {scale: [1, 2\n")
    for args in (["edit", run, "--spec", bad, "-o", tmp_path / "out"], ["animate", run, "--spec", bad, "-o", tmp_path / "out"],
                 ["reconstruct", data, "-o", tmp_path / "out", "--config", bad]):
        code, _, err = cli(*args)
        assert code == 1 and err == (f"radfield: error: {bad}: not valid YAML: expected ',' or ']', but got "
                                     "'<stream end>' (line 3, column 1)\n"), err
        assert not (tmp_path / "out").exists()


def test_edit_refuses_an_existing_output_and_needs_something_to_do(cli, scene, tmp_path):
    root, run, data, v, t = scene
    (tmp_path / "exists").mkdir()
    (tmp_path / "exists" / "keep.txt").write_text("the user's")
    code, _, err = cli("edit", run, "-o", tmp_path / "exists", "--scale", "2")
    assert code == 1 and "already exists" in err and "--force" in err
    code, _, err = cli("edit", run, "-o", tmp_path / "new")
    assert code == 1 and "nothing to do" in err
    code, _, err = cli("edit", run, "-o", tmp_path / "new", "--rotate", "1,2")
    assert code == 1 and "--rotate takes three" in err


def test_animate_a_cage_sequence_to_png_and_mp4(cli, scene, tmp_path):
    root, run_dir, data, v, t = scene
    frames_dir = tmp_path / "cages"
    for i, angle in enumerate(np.linspace(0, 33, 12)):
        a = np.radians(angle) * (v[:, 2] + 0.8)
        c, s = np.cos(a), np.sin(a)
        write_cage(frames_dir / f"pose_{i}", np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]], 1), t)
    out = tmp_path / "anim"
    # a folder of cage folders (pose_N/cage.npz), in natural order: pose_2 before pose_10
    code, stdout, err = cli("animate", run_dir, "--cages", frames_dir, "-o", out, "-q", "--fps", "10")
    assert code == 0, err
    pngs = sorted(out.glob("frame_*.png"))
    assert len(pngs) == 12
    drift = [np.abs(read_image(p) - read_image(pngs[0])).mean() for p in pngs]
    assert all(b > a for a, b in zip(drift[1:], drift[2:])), drift   # the twist grows frame by frame
    summary = json.loads((out / "animation.json").read_text())
    assert summary["frames"] == 12 and summary["consecutive_psnr"] > 15
    # a glob pattern gives the same frames
    code, _, err = cli("animate", run_dir, "--cages", str(frames_dir / "pose_*" / "cage.vtk"), "-o", tmp_path / "glob", "-q")
    assert code == 0, err
    assert np.array_equal(read_image(tmp_path / "glob" / "frame_0010.png"), read_image(out / "frame_0010.png"))
    reader = imageio.get_reader(out / "animation.mp4", "ffmpeg")
    video = [frame for frame in reader]
    reader.close()
    assert len(video) == 12 and video[0].shape == (24, 24, 3)
    first = read_image(pngs[0])[..., :3]
    assert np.abs(video[0] / 255.0 - first).mean() < 0.03       # the video holds the frames (lossy)
    assert np.abs(read_image(pngs[0]) - read_image(pngs[-1])).max() > 0.05   # the twist shows

    # a wrong topology is a one-line error and leaves nothing
    other_v, other_t = box_cage([-1, -1, -1], [1, 1, 1], 1)
    write_cage(tmp_path / "bad", other_v, other_t)
    code, _, err = cli("animate", run_dir, "--cages", str(tmp_path / "bad"), "-o", tmp_path / "anim2")
    assert code == 1 and "another topology" in err and err.count("\n") == 1
    assert not (tmp_path / "anim2").exists()


def test_animate_a_simulation(cli, scene, tmp_path):
    root, run_dir, data, v, t = scene
    spec = tmp_path / "sim.yaml"
    spec.write_text("simulate: {gravity: [0, 0, -9.8], ground: -0.8, frames: 5, fps: 10, substeps: 10}\n")
    out = tmp_path / "sim"
    code, stdout, err = cli("animate", run_dir, "--simulate", spec, "-o", out, "-q", "--orbit")
    assert code == 0, err
    assert len(list(out.glob("frame_*.png"))) == 5 and (out / "animation.mp4").is_file()
    assert len(list((out / "cages").glob("frame_*/cage.vtk"))) == 5
    summary = json.loads((out / "animation.json").read_text())
    assert summary["simulation"]["min_height"] >= -0.8 - 1e-9


def test_render_orbit_and_camera_path_with_video(cli, scene, tmp_path):
    root, run_dir, data, v, t = scene
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
    # a model file with a camera path needs no dataset (the path brings its cameras); an orbit does
    model = run_dir / "train" / "model.safetensors"
    code, _, err = cli("render", model, "-o", tmp_path / "model_path", "--camera-path", path, "-q")
    assert code == 0, err
    assert [p.name for p in sorted((tmp_path / "model_path").glob("*.png"))] == [p.name for p in images]
    assert np.array_equal(read_image(tmp_path / "model_path" / images[0].name), read_image(images[0]))
    code, _, err = cli("render", model, "-o", tmp_path / "model_orbit", "--orbit", "3")
    assert code == 1 and "--dataset" in err and not (tmp_path / "model_orbit").exists()


def test_animate_from_a_spec_file(cli, scene, tmp_path):
    root, run_dir, data, v, t = scene
    frames_dir = tmp_path / "spec_dir" / "frames"
    for i, dz in enumerate((0.0, 0.05, 0.1)):
        write_cage(frames_dir / f"f_{i}", v + np.array([0.0, 0.0, dz]) * (v[:, 2:3] + 0.8), t)
    spec = tmp_path / "spec_dir" / "anim.yaml"
    spec.write_text("animate: {cages: frames, camera: 1, fps: 12, split_threshold: 0}\n")   # relative to the spec
    code, _, err = cli("animate", run_dir, "--spec", spec, "-o", tmp_path / "a", "-q")
    assert code == 0, err
    code, _, err = cli("animate", run_dir, "--cages", frames_dir, "--camera", "1", "--fps", "12", "--split-threshold", "0",
                       "-o", tmp_path / "b", "-q")
    assert code == 0, err
    for i in range(3):                                  # the spec says what the options say
        assert np.array_equal(read_image(tmp_path / "a" / f"frame_{i:04d}.png"), read_image(tmp_path / "b" / f"frame_{i:04d}.png"))
    # --camera takes the view's frame name as render's does, or its index
    name = load_dataset(data, "test").names[1]
    code, _, err = cli("animate", run_dir, "--cages", frames_dir, "--camera", name, "--fps", "12", "--split-threshold", "0",
                       "-o", tmp_path / "named", "-q")
    assert code == 0, err
    assert np.array_equal(read_image(tmp_path / "named" / "frame_0002.png"), read_image(tmp_path / "b" / "frame_0002.png"))
    assert json.loads((tmp_path / "a" / "animation.json").read_text())["fps"] == 12
    # a simulation with render settings
    sim = tmp_path / "sim.yaml"
    sim.write_text("simulate: {ground: -0.8, frames: 3, fps: 10, substeps: 5}\nanimate: {orbit: true, elevation: 30}\n")
    code, _, err = cli("animate", run_dir, "--spec", sim, "-o", tmp_path / "s", "-q")
    assert code == 0, err
    summary = json.loads((tmp_path / "s" / "animation.json").read_text())
    assert summary["frames"] == 3 and summary["fps"] == 10 and "simulation" in summary
    # mistakes: one line, nothing written
    for text, message in (("animate: {cages: frames}\nsimulate: {}\n", "exactly one pose source"),
                          ("animate: {cages: frames, fps: -1}\n", "animate.fps"),
                          ("animate: {cages: frames, zoom: 2}\n", "unknown arguments"),
                          ("animate: {cages: frames, camera: 99}\n", "animate.camera '99': no view of that name (or index)")):
        bad = tmp_path / "spec_dir" / "bad.yaml"
        bad.write_text(text)
        code, _, err = cli("animate", run_dir, "--spec", bad, "-o", tmp_path / "bad_out")
        assert code == 1 and message in err and err.count("\n") == 1, err
        assert not (tmp_path / "bad_out").exists()
    code, _, err = cli("animate", run_dir, "--spec", spec, "--cages", frames_dir, "-o", tmp_path / "c")
    assert code == 1 and "exactly one of --cages, --simulate and --spec" in err


def test_edit_prints_the_psnr_of_a_remesh_split(cli, scene, tmp_path):
    root, run, data, v, t = scene
    spec = _spec(tmp_path / "split.yaml", [{"remesh": {"select": {"sphere": {"center": [0, 0, 0], "radius": 0.5}},
                                                       "edge_length": 0.3, "split": True, "steps": 10, "views": 3, "size": 24}}])
    code, stdout, err = cli("edit", run, "--spec", spec, "-o", tmp_path / "split_run", "-q")
    assert code == 0, err
    line = next(line for line in stdout.splitlines() if line.strip().startswith("remesh:"))
    assert "psnr_split" in line and "psnr_after" in line
    note = json.loads((tmp_path / "split_run" / "edit" / "manifest.json").read_text())["notes"][-1]
    assert note["split"] > 0 and note["psnr_after"] >= note["psnr_split"]
    code, stdout, err = cli("info", tmp_path / "split_run")
    assert code == 0, err


def test_the_boolean_phase_timings_add_up_to_its_wall_time(scene, tmp_path):
    """Every phase of a boolean is in its note (the edit prints them), and with `other` (what no
    phase measures) they add up to the operation's wall time, measured here around it."""
    import time

    from radfield.edit.boolean.operation import PHASES
    from radfield.edit.source import load_source
    from radfield.edit.spec import EditContext, apply_operations, parse_spec

    root, run, data, v, t = scene
    fld = load_source(run)
    ops = parse_spec({"operations": [{"boolean": {"op": "difference", "shape": {"sphere": {"center": [0, 0, 0], "radius": 0.25}},
                                                  "steps": 20, "views": 4, "size": 24}}]}, "test")
    start = time.perf_counter()
    out = apply_operations(fld, ops, EditContext(seed=0))
    wall = time.perf_counter() - start
    note = out.notes[-1]
    assert note["retrained"] > 0 and note["seconds"] <= wall + 0.01   # seconds are rounded to 0.01
    parts = [note[key] for key in PHASES]
    assert all(p >= 0 for p in parts), note
    assert abs(sum(parts) - note["seconds"]) <= 0.01 * len(parts), note   # to the rounding of each
    assert abs(sum(parts) - wall) <= 0.05 * wall + 0.1, (sum(parts), wall, note)
    assert note["other_seconds"] <= 0.1 * note["seconds"] + 0.02, note   # the named phases hold the time
