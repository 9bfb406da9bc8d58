"""`radfield animate`: a sequence of cage poses of a run (cage files exported from another tool, or
the built-in soft-body simulation, radfield.edit.simulate) rendered frame by frame.

Every frame deforms the run's field exactly from its rest cage to the frame's cage (as `radfield
edit` with a deform operation, radfield.edit.affine.deform_field), then renders it from one dataset
camera or an orbit around the dataset's cameras. The output folder holds frame_NNNN.png, VIDEO
(the frames as an MP4), SUMMARY (figures per frame and their means, the PSNR between consecutive
frames as a flicker measure) and, for a simulation, cages/frame_NNNN/ (each pose as a cage).
The animation spec that stands for the command's options is radfield.edit.animation_spec's.
"""

from __future__ import annotations

import glob
import json
import os
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from radfield.core.geometry.cage import read_cage, write_cage
from radfield.core.geometry.camera_path import orbit as make_orbit
from radfield.core.geometry.camera_path import orbit_from_cameras, write_video
from radfield.core.render.antialias import render_model
from radfield.datasets.images import write_image
from radfield.datasets.readers import load_dataset
from radfield.evaluation.metrics import psnr
from radfield.edit.affine import deform_field
from radfield.edit.field import Field
from radfield.errors import RadfieldError
from radfield.pipeline.config import run_config
from radfield.run import Run
from radfield.util.atomic import atomic_folder, atomic_write_text
from radfield.util.progress import progress_bar

CAGE_SUFFIXES = (".vtk", ".vtu", ".msh", ".npz")
VIDEO = "animation.mp4"
SUMMARY = "animation.json"
DEFAULT_FPS = 30.0


def to_uint8(color: torch.Tensor) -> np.ndarray:
    return (np.clip(color.detach().cpu().numpy(), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def cage_sequence(pattern: str) -> list[Path]:
    """Cage files of a folder (every .vtk/.vtu/.msh/.npz in it, else the cage.npz of each of its
    subfolders) or a glob pattern, in natural order (frame_2 before frame_10)."""
    path = Path(pattern)
    if path.is_dir():
        files = [p for p in path.iterdir() if p.is_file() and p.suffix.lower() in CAGE_SUFFIXES]
        if not files:  # a folder of cage folders, as `animate --simulate` and write_cage write them
            files = [p / "cage.npz" for p in path.iterdir() if (p / "cage.npz").is_file()]
    else:
        files = [Path(p) for p in glob.glob(os.path.expanduser(pattern)) if Path(p).is_file()]
    key = lambda p: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(p))]   # the whole path: */cage.npz
    files = sorted(files, key=key)
    if not files:
        raise RadfieldError(f"--cages {pattern}: no cage files (.vtk/.vtu/.msh/.npz) found")
    return files


def cage_poses(fld: Field, pattern: str) -> list[np.ndarray]:
    """The vertices of every cage file of `pattern` (cage_sequence), each of the run's topology."""
    poses = []
    for path in cage_sequence(pattern):
        v, t = read_cage(path)
        if t.shape != fld.cage_tets.shape or not np.array_equal(t, fld.cage_tets):
            raise RadfieldError(f"{path}: another topology ({len(v)} vertices, {len(t)} tets) than the run's cage "
                                f"({len(fld.cage_vertices)} vertices, {len(fld.cage_tets)} tets)")
        poses.append(v)
    return poses


def animate(run_dir: Path, fld: Field, output: Path, *, cages: str | None = None,
            simulation: dict[str, Any] | Path | None = None, dataset: Path | None = None, split: str = "test",
            camera: str = "0", camera_option: str = "--camera", orbit: bool = False, elevation: float = 20.0, downscale: int = 1,
            background: tuple[float, float, float] | None = None, fps: float = 0.0, gradient: str = "smooth",
            split_threshold: float = 0.5, device: torch.device | str = "cpu", quiet: bool = False,
            log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Animate the run at `run_dir`, whose field (with its cage) is `fld`, into the new folder
    `output` (layout in the module docstring): the poses are the cage files of `cages` or the
    frames of the `simulation` (checked parameters, or a YAML file with a 'simulate:' mapping:
    radfield.edit.simulate); the camera is
    the view `camera` (a frame name or an index; `camera_option` names where it was given) of the
    dataset's `split` (default dataset: the run's), or an orbit starting there.
    `background` defaults to the run's, `fps` to the simulation's, else DEFAULT_FPS. `log` gets
    the simulation's lines. Returns the summary written to SUMMARY."""
    from radfield.edit.simulate import read_simulation, simulate_cage

    from radfield.edit.affine import CAGE_GRADIENTS

    if gradient not in CAGE_GRADIENTS:   # before any work; "map" belongs to the edit operations
        raise RadfieldError(f"--gradient: one of {', '.join(CAGE_GRADIENTS)} for cage poses, got {gradient!r}")
    run = Run(run_dir)
    config = run_config(run)
    bg = background if background is not None else tuple(config["data"]["background"])
    dataset = dataset or run.dataset()
    if dataset is None:
        raise RadfieldError("--dataset is required: the run does not record its dataset")
    data = load_dataset(dataset, split=split, downscale=downscale, background=bg)
    camera = data.view_index(str(camera), camera_option)

    sim_cages = sim_figures = None
    if simulation is not None:
        if not isinstance(simulation, dict):
            simulation = read_simulation(simulation)
        sim_cages, sim_figures = simulate_cage(fld.cage_vertices, fld.cage_tets, simulation, log=log)
        poses = sim_cages
        fps = fps or simulation["fps"]
    else:
        poses = cage_poses(fld, cages)
    fps = fps or DEFAULT_FPS
    if orbit:
        params = orbit_from_cameras(data.cameras)
        cams = make_orbit(params["target"], params["radius"], elevation, len(poses), data.cameras[camera], up=params["up"])
    else:
        cams = [data.cameras[camera]] * len(poses)

    with torch.no_grad():
        render_model(fld.prims.to(device), cams[0], background=bg)   # warm-up, untimed (kernel loading)
    with atomic_folder(output, merge=True) as tmp:  # a non-empty output only with --force (cli.common.check_output)
        frames, per_frame, cache = [], [], {}
        with progress_bar(quiet) as progress:
            task = progress.add_task(f"animating {len(poses)} frames", total=len(poses))
            for i, (pose, cam) in enumerate(zip(poses, cams)):
                start = time.perf_counter()
                posed = deform_field(fld, pose, gradient=gradient, split=split_threshold or None,
                                     where=f"frame {i}", cache=cache, rebind=False)
                prims = posed.prims.to(device)
                middle = time.perf_counter()
                with torch.no_grad():
                    color = render_model(prims, cam, background=bg).color  # its own n × n rays a pixel
                end = time.perf_counter()
                frames.append(to_uint8(color))
                write_image(tmp / f"frame_{i:04d}.png", color.clamp(0, 1).cpu().numpy())
                if sim_cages is not None:
                    write_cage(tmp / "cages" / f"frame_{i:04d}", pose, fld.cage_tets)
                per_frame.append({"deform_ms": 1e3 * (middle - start), "render_ms": 1e3 * (end - middle),
                                  "primitives": len(prims), "split": posed.notes[-1]["split"]})
                progress.advance(task)
        write_video(tmp / VIDEO, frames, fps)
        consecutive = [min(99.0, float(psnr(torch.from_numpy(a / 255.0), torch.from_numpy(b / 255.0))))  # identical frames: 99 dB, not inf
                       for a, b in zip(frames, frames[1:])]
        summary = {"frames": len(frames), "fps": fps, "width": cams[0].width, "height": cams[0].height,
                   "render_ms": float(np.mean([f["render_ms"] for f in per_frame])),
                   "deform_ms": float(np.mean([f["deform_ms"] for f in per_frame])),
                   "consecutive_psnr": float(np.mean(consecutive)) if consecutive else None,
                   "consecutive_psnr_min": float(np.min(consecutive)) if consecutive else None,
                   "max_split": max(f["split"] for f in per_frame), "per_frame": per_frame}
        if sim_cages is not None:
            summary["simulation"] = sim_figures
        atomic_write_text(tmp / SUMMARY, json.dumps(summary, indent=1) + "\n")
    return summary
