"""`radfield animate` (a sequence of cage poses, or a built-in soft-body simulation, rendered to PNG
frames and an MP4) and the camera-path options of `radfield render` (--orbit, --camera-path,
--video)."""

from __future__ import annotations

import glob
import json
import os
import re
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield.errors import RadfieldError

CAGE_SUFFIXES = (".vtk", ".vtu", ".msh", ".npz")
VIDEO = "animation.mp4"
SUMMARY = "animation.json"


def to_uint8(color):
    import numpy as np

    return (np.clip(color.detach().cpu().numpy(), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_video(path: Path, frames, fps: float) -> None:
    from radfield.core.geometry.camera_path import write_video as write

    write(path, frames, fps or 30.0)


def path_cameras(cameras, names, orbit: int, elevation: float, camera_path: Path | None, fps: float):
    """The cameras `radfield render` draws: the dataset's, an orbit around them, or a camera path.
    Returns (cameras, frame names, fps)."""
    from radfield.core.geometry.camera_path import orbit as make_orbit
    from radfield.core.geometry.camera_path import orbit_from_cameras, read_nerfstudio_path

    if orbit and camera_path is not None:
        raise RadfieldError("--orbit and --camera-path exclude each other")
    if orbit < 0:
        raise RadfieldError(f"--orbit takes a frame count >= 1, got {orbit}")
    if camera_path is not None:
        cameras, path_fps = read_nerfstudio_path(camera_path)
        return cameras, [c.name for c in cameras], fps or path_fps or 30.0
    if orbit:
        if not cameras:
            raise RadfieldError("--orbit circles the dataset's cameras: give --dataset for a model file")
        params = orbit_from_cameras(cameras)
        cameras = make_orbit(params["target"], params["radius"], elevation, orbit, cameras[0], up=params["up"])
        return cameras, [c.name for c in cameras], fps or 30.0
    return cameras, names, fps or 30.0


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


def animate(
    run: Annotated[Path, typer.Argument(metavar="RUN", help="A run directory with a cage (reconstructed or edited).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder to create: frame_NNNN.png, animation.mp4, animation.json.")],
    cages: Annotated[Optional[str], typer.Option(help="Cage poses: a folder of .vtk/.vtu/.msh/.npz frames or a glob pattern (same topology as the run's cage, world frame).")] = None,
    simulate: Annotated[Optional[Path], typer.Option(help="Instead of --cages: a YAML file with a 'simulate:' mapping (built-in soft-body simulation, README 'Animation').")] = None,
    spec: Annotated[Optional[Path], typer.Option("--spec", "-s", help="Instead of --cages/--simulate: a YAML animation spec, 'animate: {cages: PATTERN, camera: ..., fps: ...}' and/or 'simulate: {...}'; its keys replace the options of the same name (README 'Animation').")] = None,
    dataset: Annotated[Optional[Path], typer.Option("--dataset", "-d", help="Dataset whose camera to use (default: the run's).")] = None,
    split: Annotated[str, typer.Option(help="Split of the dataset camera.")] = "test",
    camera: Annotated[int, typer.Option(help="Index of the dataset camera in the split.")] = 0,
    orbit: Annotated[bool, typer.Option("--orbit", help="Turn the camera once around the scene over the animation.")] = False,
    elevation: Annotated[float, typer.Option(help="Orbit elevation in degrees.")] = 20.0,
    downscale: Annotated[int, typer.Option(help="Render at 1/K of the dataset's resolution.")] = 1,
    background: Annotated[Optional[str], typer.Option(help="Background R,G,B (default: the run's, else 1,1,1).")] = None,
    fps: Annotated[float, typer.Option(help="Video frame rate (default 30, or the simulation's).")] = 0.0,
    gradient: Annotated[str, typer.Option(help="Per-primitive map: centre or tet (see radfield edit).")] = "centre",
    split_threshold: Annotated[float, typer.Option("--split-threshold", help="Split primitives straddling non-uniform tets (0: never).")] = 0.5,
    device: Annotated[str, typer.Option(help="cpu or cuda.")] = "cpu",
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
):
    """Render a sequence of cage poses of a run (e.g. a soft-body simulation exported from Houdini
    or Blender, or the built-in one) frame by frame to PNGs and an MP4.

    Every frame deforms the run's field exactly from its rest cage to the frame's cage (as
    `radfield edit` with a deform operation), then renders it from one dataset camera or an orbit.
    --spec FILE holds the same as a file: 'animate: {cages: PATTERN, camera: 0, fps: 30, ...}' or
    'simulate: {...}' (with an optional 'animate:' of render settings)."""
    import numpy as np
    import torch

    from radfield.cli.common import parse_background, progress_bar, resolve_device
    from radfield.cli.edit import load_source
    from radfield.util.atomic import atomic_folder, atomic_write_text
    from radfield.core.geometry.cage import read_cage, write_cage
    from radfield.core.geometry.camera_path import orbit as make_orbit
    from radfield.core.geometry.camera_path import orbit_from_cameras
    from radfield.delivery.metrics import psnr
    from radfield.core.render.antialias import render_model
    from radfield.datasets.images import write_image
    from radfield.datasets.readers import load_dataset
    from radfield.edit.deform import deform_field
    from radfield.pipeline.config import load_config
    from radfield.pipeline.info import run_dataset
    from radfield.pipeline.runner import CONFIG_FILE, is_run_dir

    if sum(x is not None for x in (cages, simulate, spec)) != 1:
        raise RadfieldError("give exactly one of --cages, --simulate and --spec")
    sim_params = None
    if spec is not None:
        from radfield.edit.animation import read_animation

        anim = read_animation(spec)
        cages, sim_params = anim["cages"], anim["simulate"]
        camera, split, orbit = anim.get("camera", camera), anim.get("split", split), anim.get("orbit", orbit)
        elevation, fps, downscale = anim.get("elevation", elevation), anim.get("fps", fps), anim.get("downscale", downscale)
        background, gradient = anim.get("background", background), anim.get("gradient", gradient)
        split_threshold = anim.get("split_threshold", split_threshold)
    if output.exists() and (not output.is_dir() or any(output.iterdir())):
        raise RadfieldError(f"{output}: already exists and is not an empty folder")
    if not is_run_dir(run):
        raise RadfieldError(f"{run}: not a radfield run directory")
    dev = resolve_device(device)
    fld = load_source(run)
    if not fld.has_cage:
        raise RadfieldError(f"{run}: this run has no cage to animate")
    config = load_config(run / CONFIG_FILE if (run / CONFIG_FILE).is_file() else None)
    bg = parse_background(background) if background is not None else tuple(config["data"]["background"])
    dataset = dataset or run_dataset(run)
    if dataset is None:
        raise RadfieldError("--dataset is required: the run does not record its dataset")
    data = load_dataset(dataset, split=split, downscale=downscale, background=bg)
    if not 0 <= camera < len(data.cameras):
        raise RadfieldError(f"--camera {camera}: the {split} split has {len(data.cameras)} cameras")

    sim_cages = None
    if simulate is not None or sim_params is not None:
        from radfield.edit.simulate import read_simulation, simulate_cage

        params = sim_params if sim_params is not None else read_simulation(simulate)
        sim_cages, sim_figures = simulate_cage(fld.cage_vertices, fld.cage_tets, params,
                                               log=None if quiet else (lambda m: typer.echo(m, err=True)))
        poses = sim_cages
        fps = fps or params["fps"]
    else:
        files = cage_sequence(cages)
        poses = []
        for path in files:
            v, t = read_cage(path)
            if t.shape != fld.cage_tets.shape or not np.array_equal(t, fld.cage_tets):
                raise RadfieldError(f"{path}: another topology ({len(v)} vertices, {len(t)} tets) than the run's cage "
                                    f"({len(fld.cage_vertices)} vertices, {len(fld.cage_tets)} tets)")
            poses.append(v)
    fps = fps or 30.0
    if orbit:
        params = orbit_from_cameras(data.cameras)
        cams = make_orbit(params["target"], params["radius"], elevation, len(poses), data.cameras[camera], up=params["up"])
    else:
        cams = [data.cameras[camera]] * len(poses)

    with torch.no_grad():
        render_model(fld.prims.to(dev), cams[0], background=bg)   # warm-up, untimed (kernel loading)
    with atomic_folder(output) as tmp:
        frames, per_frame, cache = [], [], {}
        with progress_bar(quiet) as progress:
            task = progress.add_task(f"animating {len(poses)} frames", total=len(poses))
            for i, (pose, cam) in enumerate(zip(poses, cams)):
                start = time.perf_counter()
                posed = deform_field(fld, pose, gradient=gradient, split=split_threshold or None,
                                     where=f"frame {i}", cache=cache)
                prims = posed.prims.to(dev)
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
    flicker = f", mean PSNR between consecutive frames {summary['consecutive_psnr']:.2f} dB" if consecutive else ""
    typer.echo(f"animated {len(frames)} frames ({cams[0].width}x{cams[0].height}) to {output / VIDEO}: "
               f"{summary['render_ms']:.1f} ms/frame render, {summary['deform_ms']:.1f} ms/frame deform{flicker}")
