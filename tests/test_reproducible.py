"""The whole pipeline on the 'objects' scene (separate objects, a torus, thin rods, RGBA, no
mesh.ply: the visual hull), the same command giving the same model (fTetWild's cage is not
deterministic, nothing training uses depends on it), a SIGKILLed and resumed run equal to a fresh
one, and `--no-cage`."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from radfield.core.geometry.envelope import read_envelope, signed_distance
from radfield.model_file import load_model
from radfield.demo.static import generate_scene
from radfield.demo.scenes import get_scene
from radfield.pipeline.runner import read_manifest
from radfield.stages.train import CHECKPOINT

STAGES = ("sfm", "data", "triangulate", "envelope", "tetra", "init", "train", "eval")
FAST = ["--set", "train.iterations=30"]
# tiny and quick for the determinism checks: few primitives, a coarse hull and envelope
TINY = ["--set", "init.num_points=150", "--set", "envelope.hull_resolution=32", "--set", "envelope.target_faces=300"]


@pytest.fixture(scope="module")
def objects(tmp_path_factory) -> Path:
    return generate_scene("objects", tmp_path_factory.mktemp("data") / "objects", n_train=8, n_test=2, size=32)


def figures(run_dir: Path, stage: str) -> dict:
    return read_manifest(run_dir / stage)["figures"]


def test_objects_scene_has_no_mesh_and_the_traits_it_promises(objects):
    scene = get_scene("objects")
    kinds = [type(p).__name__ for p in scene.primitives]
    assert "Torus" in kinds and kinds.count("Cylinder") >= 2 and len(kinds) >= 5
    assert min(p.radius for p in scene.primitives if type(p).__name__ == "Cylinder") <= 0.025  # thin rods
    assert not (objects / "mesh.ply").exists()
    assert json.loads((objects / "scene.json").read_text())["name"] == "objects"


def test_torus_intersection_matches_ray_marching_its_distance_function():
    """The quartic's first root against the first sign change of the exact torus SDF along the
    ray (a dense march), normals against the SDF's finite-difference gradient."""
    from radfield.demo.shapes import Material, Torus

    torus = Torus((0.2, 0.1, 0.3), (0.3, 0.2, 1.0), 0.5, 0.15, Material((1.0, 0.0, 0.0)))
    frame, centre = torus.frame, np.asarray(torus.center)

    def sdf(p):
        local = (p - centre) @ frame
        return np.hypot(np.hypot(local[..., 0], local[..., 1]) - 0.5, local[..., 2]) - 0.15

    rng = np.random.default_rng(0)
    o = np.array([3.0, 1.0, 2.0])
    d = rng.normal(size=(300, 3)) * 0.15 + (centre - o) / np.linalg.norm(centre - o)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, normal = torus.intersect(o, d)
    hit = np.isfinite(t)
    assert 0.2 < hit.mean() < 0.8
    steps = np.linspace(2.0, 5.0, 6001)  # the torus lies 2.7-4.1 from o
    values = sdf(o + steps[None, :, None] * d[:, None])
    inside = values < 0
    assert np.array_equal(inside.any(1), hit)  # the same rays hit
    assert np.abs(steps[inside[hit].argmax(1)] - t[hit]).max() < 1e-3  # at the first crossing
    p = o + t[hit, None] * d[hit]
    gradient = np.stack([(sdf(p + e) - sdf(p - e)) / 2e-6 for e in np.eye(3) * 1e-6], 1)
    assert np.allclose(normal[hit], gradient / np.linalg.norm(gradient, axis=1, keepdims=True), atol=1e-5)


def test_pipeline_on_the_objects_scene_and_the_same_command_gives_the_same_model(objects, tmp_path, cli):
    """Defaults except 30 iterations, twice in fresh run directories: byte-identical models."""
    runs = [tmp_path / "run1", tmp_path / "run2"]
    for run_dir in runs:
        code, out, err = cli("reconstruct", objects, "-o", run_dir, "-q", *FAST)
        assert code == 0, err
        assert ("stages: sfm not applicable, data ran, triangulate not applicable, envelope ran, tetra ran, init ran, "
                "train ran, bind ran, bake ran, eval ran") in out
        assert "warning" not in err  # no fallback on this scene
    run_dir = runs[0]
    envelope = figures(run_dir, "envelope")
    assert envelope["source"] == envelope["method"] == "hull" and envelope["fallback"] is None
    assert envelope["points_outside"] == 0 and envelope["faces"] <= 1000
    assert figures(run_dir, "tetra")["fallback"] is None and figures(run_dir, "init")["bound"] is True
    # the envelope holds every object of the scene (sampled on the analytic shapes' meshes)
    surface = np.concatenate([np.asarray(p.mesh().triangulate().points) for p in get_scene("objects").primitives])
    assert (signed_distance(surface, *read_envelope(run_dir / "envelope" / "envelope.ply")) < 0).all()
    assert np.isfinite(figures(run_dir, "eval")["psnr"]) and figures(run_dir, "eval")["psnr"] > 10
    model = [(r / "train" / "model.safetensors").read_bytes() for r in runs]
    assert model[0] == model[1]
    for name in ("envelope/envelope.ply", "init/init.safetensors"):
        assert (runs[0] / name).read_bytes() == (runs[1] / name).read_bytes(), name


def _reconstruct(*args) -> list[str]:
    return [sys.executable, "-m", "radfield.cli.main", "reconstruct", *map(str, args)]


def test_a_killed_and_resumed_run_equals_a_fresh_run(objects, tmp_path, cli):
    """SIGKILL during training, after the first checkpoint; resumed in the same run directory,
    the model equals (bytes) that of an uninterrupted run in another run directory."""
    sets = [*TINY, "--set", "train.iterations=60", "--set", "train.checkpoint_every=10"]
    killed = tmp_path / "killed"
    checkpoint = killed / "train.work" / CHECKPOINT
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    process = subprocess.Popen(_reconstruct(objects, "-o", killed, "-q", *sets), env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 300
    while not checkpoint.exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert checkpoint.exists(), process.stderr.read().decode() if process.poll() is not None else "no checkpoint"
    process.send_signal(signal.SIGKILL)
    assert process.wait() == -signal.SIGKILL
    assert not (killed / "train" / "model.safetensors").exists()  # killed before training ended

    code, _, err = cli("reconstruct", objects, "-o", killed, *sets)
    # it must resume (a restart from step 0 would equal the fresh run trivially)
    assert code == 0 and "train: resuming from the checkpoint at step" in err, err
    step = int(err.split("resuming from the checkpoint at step")[1].split()[0])
    assert 10 <= step < 60
    assert [read_manifest(killed / s)["stage"] for s in STAGES] == list(STAGES)

    code, _, err = cli("reconstruct", objects, "-o", tmp_path / "fresh", "-q", *sets)
    assert code == 0, err
    assert (killed / "train" / "model.safetensors").read_bytes() == \
        (tmp_path / "fresh" / "train" / "model.safetensors").read_bytes()


def test_no_cage_skips_envelope_and_tetra_on_purpose(objects, tmp_path, cli):
    run_dir = tmp_path / "run"
    code, out, err = cli("reconstruct", objects, "-o", run_dir, "-q", "--no-cage", "--until", "init", *TINY)
    assert code == 0, err
    assert "envelope not applicable, tetra not applicable, init ran" in out
    reason = read_manifest(run_dir / "envelope")["reason"]
    assert "envelope.source is none" in reason and "on purpose" in reason
    assert read_manifest(run_dir / "tetra")["reason"] == "no envelope to fill (see the envelope stage)"
    init = figures(run_dir, "init")
    assert init["bound"] is False and init["cage_samples"] == 0 and init["source"] == "random"
    with np.load(run_dir / "init" / "binding.npz") as binding:
        assert (binding["tet"] == -1).all() and len(binding["tet"]) == 150
    # the same through the config key
    code, out, _ = cli("reconstruct", objects, "-o", tmp_path / "run2", "-q", "--set", "envelope.source=none",
                       "--until", "init", *TINY)
    assert code == 0 and (run_dir / "init" / "init.safetensors").read_bytes() == \
        (tmp_path / "run2" / "init" / "init.safetensors").read_bytes()


def test_stage_fallbacks_are_recorded_and_printed_as_one_warning(objects, tmp_path, cli, monkeypatch):
    """The wrap and fTetWild forced to fail inside a real run: the envelope is the convex hull,
    the cage the Delaunay fallback; both in the figures, each one warning line, and init still
    draws its centres inside the envelope."""
    import pymeshlab
    import pytetwild

    from radfield.core.geometry import envelope

    def broken_wrap(*args, **kwargs):
        raise pymeshlab.PyMeshLabException("forced wrap failure")

    monkeypatch.setattr(envelope, "_wrap", broken_wrap)
    monkeypatch.setattr(pytetwild, "tetrahedralize", lambda *a, **k: (np.zeros((0, 3)), np.zeros((0, 4), int)))
    run_dir = tmp_path / "run"
    code, out, err = cli("reconstruct", objects, "-o", run_dir, "-q", "--until", "init", *TINY)
    assert code == 0, err
    warnings = [line for line in err.splitlines() if "warning" in line]
    assert len(warnings) == 2 and warnings[0].startswith("radfield: warning: envelope: fell back to the convex_hull")
    assert warnings[1].startswith("radfield: warning: tetra: fell back to a delaunay cage")
    assert figures(run_dir, "envelope")["fallback"] == "convex_hull"
    assert "forced wrap failure" in figures(run_dir, "envelope")["fallback_reason"]
    assert figures(run_dir, "tetra")["fallback"] == "delaunay" and "no tets" in figures(run_dir, "tetra")["fallback_reason"]
    means = load_model(run_dir / "init" / "init.safetensors").means.double().numpy()
    assert (signed_distance(means, *read_envelope(run_dir / "envelope" / "envelope.ply")) < 0).all()
