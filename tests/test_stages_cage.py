"""The stages that make the cage (the photo front end): sfm -> data -> envelope -> tetra -> init (cage and binding),
on 8 fox_small photos and on tiny generated scenes, plus the error paths through the CLI."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import meshio
import numpy as np
import pytest

from radfield.errors import RadfieldError
from radfield.model_file import load_model
from radfield.datasets.images import read_image, write_image
from radfield.demo.static import generate_scene
from radfield.datasets import scene as data
from radfield.pipeline.config import load_config
from radfield.core.geometry.envelope import read_envelope, signed_distance
from radfield.evaluation.evaluate import eval_report
from radfield.pipeline.info import run_info
from radfield.pipeline.runner import read_manifest, run_pipeline
from radfield.run import Run
from radfield.stages.registry import stages
from radfield.core.geometry.cage import bind_to_cage, locate_points, read_cage, write_binding

FRONT = ["sfm", "data", "envelope", "tetra", "init"]


def config(*sets: str) -> dict:
    return load_config(sets=["init.num_points=300", "envelope.target_faces=300", *sets])


def run_until(stage: str, source: Path, run_dir: Path, *sets: str) -> dict[str, str]:
    return run_pipeline(stages(), run_dir, config(*sets), input_path=source, until_stage=stage, quiet=True)


def fox_photos(fox: Path, dst: Path, count: int = 8) -> Path:
    """The first `count` fox_small photos (consecutive views) copied into `dst`."""
    dst.mkdir(parents=True)
    for path in sorted((fox / "images").glob("*.jpg"))[:count]:
        shutil.copy(path, dst / path.name)
    return dst


def noise_photos(dst: Path, count: int, shape: tuple[int, int], start: int = 0) -> list[str]:
    rng = np.random.default_rng(start)
    dst.mkdir(parents=True, exist_ok=True)
    names = [f"noise{k}.png" for k in range(start, start + count)]
    for name in names:
        cv2.imwrite(str(dst / name), rng.integers(0, 256, (*shape, 3), dtype=np.uint8))
    return names


def stage_dirs(run_dir: Path) -> dict[str, tuple[int, bytes]]:
    """Every file of the stage directories (not the run's config or hash cache)."""
    return {str(p.relative_to(run_dir)): (p.stat().st_mtime_ns, p.read_bytes())
            for name in FRONT for p in sorted((run_dir / name).rglob("*")) if p.is_file()}


def leftovers(run_dir: Path) -> list[str]:
    return [p.name for p in run_dir.iterdir() if ".tmp-" in p.name or ".old-" in p.name]


def assert_bound(run_dir: Path) -> np.ndarray:
    """The init stage's centres lie in the envelope and its binding reproduces them; returns the centres."""
    vertices, tets = read_cage(run_dir / "tetra" / "cage.npz")
    means = load_model(run_dir / "init" / "init.safetensors").means.double().numpy()
    with np.load(run_dir / "init" / "binding.npz") as binding:
        tet, bary = binding["tet"], binding["bary"]
    assert tet.shape == (len(means),) and (tet >= 0).all() and np.allclose(bary.sum(1), 1)
    assert np.allclose(np.einsum("pk,pkd->pd", bary, vertices[tets[tet]]), means, atol=1e-5)
    # centres are drawn inside the envelope, which the cage approximates: nearly all are in a tet
    assert (signed_distance(means, *read_envelope(run_dir / "envelope" / "envelope.ply")) < 1e-6).all()
    assert (bary.min(1) >= -1e-9).mean() > 0.95
    return means


# --- photos ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def photo_run(tmp_path_factory, fox) -> tuple[Path, Path]:
    """(photos, run) of the front end on 8 fox photos."""
    root = tmp_path_factory.mktemp("fox")
    photos = fox_photos(fox, root / "photos")
    status = run_until("init", photos, root / "run")
    assert status == dict.fromkeys(FRONT, "ran") | {"triangulate": "not applicable"}
    assert read_manifest(root / "run" / "triangulate")["reason"] == "the dataset has its own SfM points"
    return photos, root / "run"


def test_photos_become_a_posed_dataset_with_a_cage(photo_run):
    photos, run_dir = photo_run
    info = run_info(run_dir)
    sfm, data, envelope, tetra = (info["stages"][name] for name in FRONT[:4])
    assert (sfm["registered_images"], sfm["total_images"]) == (8, 8)
    assert sfm["points"] > 200 and 0 < sfm["reprojection_error"] < 1.5
    # the data stage read the sfm stage's COLMAP folder: undistorted photos, normalised frame
    posed = run_dir / "sfm" / "colmap"
    assert data["format"] == "colmap" and data["points"] == sfm["points"] and data["images"] == 8
    scene = json.loads((run_dir / "data" / "scene.json").read_text())
    assert scene["root"] == str(posed) and all(Path(v["image"]).parent == posed / "images"
                                               for v in scene["splits"]["train"])
    assert info["normalization"] == str(posed / "normalization.json") and Run(run_dir).dataset() == posed
    assert envelope["source"] == "points" and envelope["faces"] <= 300 and envelope["points_outside"] == 0
    assert 50 < tetra["tets"] < 5000 and tetra["vertices"] > 4
    assert cv2.imread(str(run_dir / "envelope" / "envelope.png")).shape[:2] == (data["height"], data["width"])
    # the envelope holds the SfM inliers; the cage holds the primitives, bound to its tets
    with np.load(run_dir / "data" / "points.npz") as points:
        xyz = points["xyz"]
    outside = signed_distance(xyz, *read_envelope(run_dir / "envelope" / "envelope.ply")) > 0
    assert outside.sum() <= envelope["outliers"]
    assert info["stages"]["init"]["source"] == "points" and info["stages"]["init"]["cage_samples"] == 30
    means = assert_bound(run_dir)
    from_points = (np.abs(means[:, None] - xyz[None]).max(-1) < 1e-6).any(1)
    assert from_points.sum() == 270  # the rest were sampled in the cage's volume


def test_a_failing_sfm_leaves_the_run_as_it_was(tmp_path, cli, fox):
    photos = fox_photos(fox, tmp_path / "photos")
    run_dir = tmp_path / "run"
    args = ["reconstruct", photos, "-o", run_dir, "-q", "--until", "data"]
    assert cli(*args)[0] == 0
    before = stage_dirs(run_dir)
    height, width = cv2.imread(str(next(photos.iterdir()))).shape[:2]
    noise = noise_photos(photos, 3, (height, width))  # the user adds photos that cannot register
    code, out, err = cli(*args, "--set", "sfm.min_registered_fraction=1.0")
    assert code == 1 and out == "" and len(err.strip().splitlines()) == 1, err
    assert "only 8 of 11 images registered" in err and all(name in err for name in noise)
    assert stage_dirs(run_dir) == before and not leftovers(run_dir)


def test_posed_photos_without_points_are_triangulated(tmp_path, fox):
    """fox_small's own poses (nerfstudio, with lens distortion) for 8 photos, no points: the envelope
    comes from features triangulated with those poses, in the dataset's frame."""
    photos = fox_photos(fox, tmp_path / "photos")
    meta = json.loads((fox / "transforms.json").read_text())
    frames = sorted(meta["frames"], key=lambda frame: frame["file_path"])[:8]
    for frame in frames:
        frame["file_path"] = str(photos / Path(frame["file_path"]).name)
    (tmp_path / "posed").mkdir()
    (tmp_path / "posed" / "transforms.json").write_text(json.dumps(meta | {"frames": frames}))
    run_dir = tmp_path / "run"
    status = run_until("tetra", tmp_path / "posed", run_dir)
    assert status == {"sfm": "not applicable", "data": "ran", "triangulate": "ran", "envelope": "ran", "tetra": "ran"}
    figures = read_manifest(run_dir / "envelope")["figures"]
    assert figures["source"] == "triangulate" and figures["inliers"] > 200 and figures["points_outside"] == 0
    # the triangulate stage's points, read by the envelope (triangulated once)
    with np.load(run_dir / "triangulate" / "triangulated.npz") as triangulated:
        count = len(triangulated["xyz"])
    assert figures["inliers"] + figures["outliers"] == count
    assert read_manifest(run_dir / "triangulate")["figures"] == {"points": count, "views": 7}   # 1 of 8 held out
    # the envelope is in the dataset's frame: in front of every camera, around what they look at
    vertices, _ = read_envelope(run_dir / "envelope" / "envelope.ply")
    for camera in data.load_scene(run_dir / "data" / "scene.json").train_cameras:
        local = vertices @ camera.w2c[:3, :3].numpy().T + camera.w2c[:3, 3].numpy()
        assert (local[:, 2] > 0).all()
        u, v = (camera.K.numpy() @ local.mean(0))[:2] / local.mean(0)[2]
        assert 0 < u < camera.width and 0 < v < camera.height


# --- sfm errors -----------------------------------------------------------------------------------


@pytest.mark.parametrize("case, message", [
    ("two", "found 2 images"),
    ("noise", "do not overlap"),
])
def test_sfm_errors_are_one_line_and_write_nothing(tmp_path, cli, case, message):
    photos = tmp_path / "photos"
    noise_photos(photos, 2 if case == "two" else 5, (120, 160))
    run_dir = tmp_path / "run"
    code, out, err = cli("reconstruct", photos, "-o", run_dir, "-q")
    assert code == 1 and len(err.strip().splitlines()) == 1 and message in err and err.startswith("radfield: error: sfm:")
    assert not (run_dir / "sfm").exists() and not leftovers(run_dir)


def test_an_unreadable_photo_is_named_before_anything_runs(tmp_path, cli):
    photos = tmp_path / "photos"
    noise_photos(photos, 4, (60, 80))
    (photos / "broken.jpg").write_bytes(b"not a jpeg")
    code, _, err = cli("reconstruct", photos, "-o", tmp_path / "run", "-q")
    assert code == 1 and len(err.strip().splitlines()) == 1 and "broken.jpg" in err
    assert not (tmp_path / "run").exists()


# --- generated scenes -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def blobs(tmp_path_factory) -> Path:
    return generate_scene("blobs", tmp_path_factory.mktemp("data") / "blobs", n_train=6, n_test=2, size=32)


def test_envelope_from_the_dataset_mesh_and_its_cage(blobs, tmp_path):
    run_dir = tmp_path / "run"
    status = run_until("init", blobs, run_dir)
    assert status == {"sfm": "not applicable", "data": "ran", "triangulate": "not applicable", "envelope": "ran",
                      "tetra": "ran", "init": "ran"}
    manifest = read_manifest(run_dir / "sfm")
    assert manifest["reason"] == f"posed dataset: poses come from {blobs.resolve() / 'transforms_train.json'}"
    assert read_manifest(run_dir / "triangulate")["reason"] == "the dataset has its own mesh.ply"
    envelope = read_manifest(run_dir / "envelope")["figures"]
    assert envelope["source"] == "mesh" and envelope["faces"] <= 300 and envelope["self_intersections"] == 0
    with np.load(run_dir / "data" / "points.npz") as points:
        mesh = points["mesh_vertices"]
    assert (signed_distance(mesh, *read_envelope(run_dir / "envelope" / "envelope.ply")) < 0).all()
    vertices, tets = read_cage(run_dir / "tetra" / "cage.npz")
    assert read_manifest(run_dir / "tetra")["figures"] | {"volume": 0} == {"tets": len(tets), "vertices": len(vertices),
                                                                           "volume": 0, "fallback": None,
                                                                           "fallback_reason": None}
    assert meshio.read(run_dir / "tetra" / "cage.vtk").cells_dict["tetra"].shape == tets.shape
    assert (locate_points(vertices, tets, mesh)[0] >= 0).mean() > 0.99  # the cage follows the envelope
    assert_bound(run_dir)


def test_visual_hull_from_alpha_masks(blobs, tmp_path):
    run_dir = tmp_path / "run"
    run_until("envelope", blobs, run_dir, "envelope.source=hull", "envelope.hull_resolution=32")
    figures = read_manifest(run_dir / "envelope")["figures"]
    assert figures["source"] == "hull" and figures["faces"] > 50 and figures["voxels"] > 0
    with np.load(run_dir / "data" / "points.npz") as points:
        mesh = points["mesh_vertices"]
    # carving is conservative: the object is inside its hull
    assert (signed_distance(mesh, *read_envelope(run_dir / "envelope" / "envelope.ply")) < 0).all()


def rgb_copy(blobs: Path, dst: Path) -> Path:
    """The scene without what an envelope is built from: no mesh.ply, RGB images without alpha."""
    shutil.copytree(blobs, dst)
    (dst / "mesh.ply").unlink()
    for image in dst.rglob("*.png"):
        write_image(image, read_image(image)[..., :3] + (1 - read_image(image)[..., 3:]))
    return dst


def test_too_few_triangulated_points_means_no_cage(blobs, tmp_path):
    source = rgb_copy(blobs, tmp_path / "rgb")  # 6 views of 32x32 pixels: too small for features
    run_dir = tmp_path / "run"
    status = run_until("init", source, run_dir)
    assert status["triangulate"] == status["envelope"] == status["tetra"] == "not applicable"
    assert status["init"] == "ran"
    info = run_info(run_dir)
    assert "points triangulated from the 6 posed training views" in info["stages"]["triangulate"]["reason"]
    assert info["stages"]["envelope"]["reason"] == "no triangulated points (see the triangulate stage)"
    assert info["stages"]["tetra"]["reason"] == "no envelope to fill (see the envelope stage)"
    assert info["stages"]["init"]["source"] == "random" and info["stages"]["init"]["bound"] is False
    with np.load(run_dir / "init" / "binding.npz") as binding:
        assert (binding["tet"] == -1).all() and len(binding["tet"]) == 300
    # asked for by name, the missing points are an error of the stage that needs them
    for key, stage in (("envelope.source", "envelope"), ("init.source", "init")):
        with pytest.raises(RadfieldError, match=f"{stage}: config key {key} is triangulate but .*triangulate stage"):
            run_until("init", source, run_dir, f"{key}=triangulate")


@pytest.mark.parametrize("args, key", [
    (["--set", "envelope.method=marching"], "envelope.method"),
    (["--set", "envelope.source=photos"], "envelope.source"),
    (["--set", "envelope.target_faces=3"], "envelope.target_faces"),
    (["--set", "tetra.edge_length_fac=0"], "tetra.edge_length_fac"),
    (["--set", "sfm.min_registered_fraction=1.5"], "sfm.min_registered_fraction"),
    (["--set", "sfm.camera_model=THIN_PRISM"], "sfm.camera_model"),
    (["--set", "init.cage_fraction=2"], "init.cage_fraction"),
    (["--set", "init.source=triangulate"], "init.source"),   # the scene has a mesh.ply
    (["--set", "train.frequency_cap=-1"], "train.frequency_cap"),
    (["--set", "train.frequency_bound=-1"], "train.frequency_bound"),
    (["--set", "train.nonnegative_density=200"], "train.nonnegative_density"),
])
def test_front_end_config_errors_name_the_key(blobs, tmp_path, cli, args, key):
    code, _, err = cli("reconstruct", blobs, "-o", tmp_path / "run", *args)
    assert code == 1 and len(err.strip().splitlines()) == 1 and key in err, err
    assert not (tmp_path / "run").exists()


def test_a_missing_envelope_source_fails_in_its_stage_only(blobs, tmp_path, cli):
    run_dir = tmp_path / "run"
    code, _, err = cli("reconstruct", blobs, "-o", run_dir, "-q", "--until", "tetra",
                       "--set", "envelope.source=points")
    assert code == 1 and err.strip() == "radfield: error: envelope: config key envelope.source is points but the " \
                                        "dataset has no SfM points"
    assert (run_dir / "data" / "manifest.json").is_file() and not (run_dir / "envelope").exists()
    assert not leftovers(run_dir)


# --- binding --------------------------------------------------------------------------------------


def test_bind_to_cage_extrapolates_outside_points(tmp_path):
    # a unit cube split into 6 tets around its diagonal
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    tets = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])
    signed = np.linalg.det(cube[tets[:, 1:]] - cube[tets[:, :1]])
    tets[signed < 0] = tets[signed < 0][:, [0, 2, 1, 3]]
    np.savez(tmp_path / "cage.npz", vertices=cube, tets=tets)
    points = np.array([[0.2, 0.5, 0.7], [1.3, 0.5, 0.5], [-0.4, 1.2, 0.1]])
    tet, bary = bind_to_cage(points, tmp_path / "cage.npz")
    assert (tet >= 0).all() and np.allclose(bary.sum(1), 1)
    assert np.allclose(np.einsum("pk,pkd->pd", bary, cube[tets[tet]]), points)  # exact, inside or out
    assert (bary[0] >= 0).all() and (bary[1:].min(1) < 0).all()
    # a point just outside a face binds to the tet behind that face
    behind = locate_points(cube, tets, [[1 - 1e-3, 0.3, 0.6]])[0]
    assert np.array_equal(bind_to_cage([[1.01, 0.3, 0.6]], tmp_path / "cage.npz")[0], behind)
    write_binding(tmp_path / "none.npz", points, None)
    with np.load(tmp_path / "none.npz") as unbound:
        assert (unbound["tet"] == -1).all() and unbound["bary"].shape == (3, 4)


def test_eval_of_a_photo_run_uses_the_posed_photos(photo_run, tmp_path):
    _, run_dir = photo_run
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    (run / "train").mkdir()
    shutil.copy(run / "init" / "init.safetensors", run / "train" / "model.safetensors")
    metrics = eval_report(run, None, "test", tmp_path / "report")
    assert metrics["views"] == 1 and metrics["width"] == run_info(run)["stages"]["data"]["width"]
