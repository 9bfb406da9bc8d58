"""Structure from motion (radfield.datasets.sfm, pycolmap) on real photos and on images it must refuse."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from radfield.core.geometry.cameras import Camera, look_at, opengl_to_opencv
from radfield.errors import RadfieldError
from radfield.pipeline.config import load_defaults
from radfield.datasets.formats.colmap import read_colmap
from radfield.datasets.sfm import compare_poses, run_sfm


def cfg(section: str, **overrides) -> dict:
    """A config section of pipeline.yaml with some keys changed."""
    return {**load_defaults()[section], **overrides}


def _fox_images(fox: Path, dst: Path, count: int, scale: float = 0.8) -> list[str]:
    """The first `count` fox_small photos (consecutive views), downscaled into `dst`."""
    dst.mkdir(parents=True, exist_ok=True)
    names = sorted(p.name for p in (fox / "images").glob("*.jpg"))[:count]
    for name in names:
        image = cv2.imread(str(fox / "images" / name))
        cv2.imwrite(str(dst / name), cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA))
    return names


def _noise_images(dst: Path, count: int, shape=(180, 240), seed: int = 0) -> list[str]:
    rng = np.random.default_rng(seed)
    dst.mkdir(parents=True, exist_ok=True)
    names = [f"noise{k}.png" for k in range(count)]
    for name in names:
        cv2.imwrite(str(dst / name), rng.integers(0, 256, (*shape, 3), dtype=np.uint8))
    return names


def _leftovers(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if ".tmp-" in p.name or ".old-" in p.name]


# ---------------------------------------------------------------- SfM


def test_sfm_registers_a_tiny_real_capture(tmp_path, fox):
    names = _fox_images(fox, tmp_path / "photos", 8)
    out = tmp_path / "sfm"
    figures = run_sfm(tmp_path / "photos", out, cfg("sfm", num_threads=2))

    assert figures["total_images"] == 8 and figures["registered_images"] == 8
    assert figures["points"] > 200
    assert 0 < figures["reprojection_error"] < 1.5
    assert sorted(p.name for p in (out / "images").iterdir()) == names
    assert {"cameras.bin", "images.bin", "points3D.bin"} <= {p.name for p in (out / "sparse").iterdir()}
    assert (out / "points.ply").stat().st_size > 0
    assert json.loads((out / "sfm.json").read_text())["matcher"] == "exhaustive"
    assert not _leftovers(tmp_path)

    cameras = [view.camera for view in read_colmap(out, "all")[0]]  # the output is a COLMAP dataset
    assert [c.name for c in cameras] == [Path(n).stem for n in names]
    # normalised: every camera centre within the target radius 1 of the points' median
    assert max(float(c.center.norm()) for c in cameras) == pytest.approx(1.0, abs=1e-6)
    norm = json.loads((out / "normalization.json").read_text())
    assert len(norm["center"]) == 3 and norm["scale"] > 0

    meta = json.loads((fox / "transforms.json").read_text())
    reference = [
        Camera(meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"], int(meta["w"]), int(meta["h"]),
               opengl_to_opencv(torch.tensor(f["transform_matrix"])), f["file_path"])
        for f in meta["frames"]
    ]
    errors = compare_poses(cameras, reference)
    assert errors["matched"] == 8
    assert errors["rotation_deg_max"] < 3.0
    assert errors["position_pct_max"] < 5.0


def test_sfm_sequential_matching_for_larger_sets(tmp_path, fox):
    _fox_images(fox, tmp_path / "photos", 8, scale=0.6)
    (tmp_path / "sfm").mkdir()
    (tmp_path / "sfm" / "stale.txt").write_text("from an older run")
    figures = run_sfm(tmp_path / "photos", tmp_path / "sfm", cfg("sfm", exhaustive_max_images=4, sequential_overlap=3))
    assert figures["registered_images"] == 8
    assert not (tmp_path / "sfm" / "stale.txt").exists() and not _leftovers(tmp_path)  # replaced whole
    assert json.loads((tmp_path / "sfm" / "sfm.json").read_text())["matcher"] == "sequential"


def test_sfm_needs_three_images(tmp_path):
    _noise_images(tmp_path / "photos", 2)
    with pytest.raises(RadfieldError, match="found 2 images"):
        run_sfm(tmp_path / "photos", tmp_path / "sfm", cfg("sfm"))


def test_sfm_names_unreadable_images(tmp_path):
    _noise_images(tmp_path / "photos", 3)
    (tmp_path / "photos" / "broken.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(RadfieldError, match="broken.jpg"):
        run_sfm(tmp_path / "photos", tmp_path / "sfm", cfg("sfm"))
    assert not (tmp_path / "sfm").exists()


def test_sfm_images_without_overlap_fail_cleanly(tmp_path):
    _noise_images(tmp_path / "photos", 5)
    out = tmp_path / "sfm"
    out.mkdir()
    (out / "previous.txt").write_text("an earlier good run")
    with pytest.raises(RadfieldError, match="do not overlap") as info:
        run_sfm(tmp_path / "photos", out, cfg("sfm"))
    assert "\n" not in str(info.value)
    assert [p.name for p in out.iterdir()] == ["previous.txt"]  # the earlier output is untouched
    assert not _leftovers(tmp_path)


def test_sfm_lists_unregistered_images(tmp_path, fox):
    names = _fox_images(fox, tmp_path / "photos", 6)
    shape = cv2.imread(str(tmp_path / "photos" / names[0])).shape[:2]  # same size: one shared camera
    noise = _noise_images(tmp_path / "photos", 3, shape)
    with pytest.raises(RadfieldError, match="only 6 of 9 images registered") as info:
        run_sfm(tmp_path / "photos", tmp_path / "sfm", cfg("sfm", min_registered_fraction=0.9))
    assert all(name in str(info.value) for name in noise)
    assert not (tmp_path / "sfm").exists()


def test_compare_poses_undoes_a_similarity():
    rng = np.random.default_rng(1)
    reference = [Camera(100, 100, 50, 50, 100, 100, look_at(3 * np.r_[np.cos(a), np.sin(a), 0.5], (0, 0, 0)), f"dir/{k}.png")
                 for k, a in enumerate(np.linspace(0, 2 * np.pi, 10, endpoint=False))]
    R = torch.tensor(cv2.Rodrigues(rng.normal(size=3))[0])
    sim = torch.eye(4, dtype=torch.float64)
    sim[:3, :3], sim[:3, 3] = 0.3 * R, torch.tensor([1.0, -2.0, 0.5])
    recovered = []
    for k, cam in enumerate(reference):
        c2w = sim @ cam.c2w
        c2w[:3, :3] /= 0.3
        if k == 4:  # one camera turned by 5 degrees about its own optical axis
            c2w[:3, :3] = c2w[:3, :3] @ torch.tensor(cv2.Rodrigues(np.r_[0, 0, np.radians(5)])[0])
        recovered.append(Camera(100, 100, 50, 50, 100, 100, c2w, Path(cam.name).name))
    errors = compare_poses(recovered, reference)
    assert errors["matched"] == 10
    assert errors["scale"] == pytest.approx(1 / 0.3)
    assert errors["position_pct_max"] < 1e-6
    assert errors["rotation_deg_max"] == pytest.approx(5.0, abs=1e-6)
    assert errors["rotation_deg_median"] < 1e-6
