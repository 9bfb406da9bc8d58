"""`radfield render`: draw every camera of a dataset split (or an orbit around them, or a camera
path) with a trained model into a folder of PNGs, and optionally an MP4.

For a run directory every default is the run's own (RUN/config.yaml): the dataset it trained on
(radfield.run.Run.dataset), its split rule (data.test_every), background, downscale and near plane;
`options` ({"data.background": [...], "data.downscale": 2, "render.near": 0.05}) win over them.
A run or a model file is drawn as it was trained: each pixel the mean of the model's own n × n
rays (its `supersample`, core/antialias.render_model).
The frames are written into a temporary folder beside the output and moved into place at the end,
so a failed render leaves no partial output.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from radfield.util.atomic import atomic_folder
from radfield.core.geometry.camera_path import orbit as make_orbit
from radfield.core.geometry.camera_path import orbit_from_cameras, read_nerfstudio_path, write_video
from radfield.errors import RadfieldError
from radfield.delivery.io import load_model
from radfield.core.render.antialias import render_model
from radfield.util.timing import clock
from radfield.datasets.images import write_image
from radfield.pipeline.config import load_config
from radfield.datasets.scene import load_split
from radfield.run import Run

DEFAULT_FPS = 30.0


def path_cameras(cameras, names, orbit: int, elevation: float, camera_path: Path | None, fps: float):
    """The cameras to draw instead of a split's: an orbit of `orbit` frames around `cameras` (at
    `elevation` degrees), or the cameras of a nerfstudio camera-path file. Returns (cameras,
    frame names, fps): `fps`, else the camera path's, else DEFAULT_FPS."""
    if orbit and camera_path is not None:
        raise RadfieldError("--orbit and --camera-path exclude each other")
    if orbit < 0:
        raise RadfieldError(f"--orbit takes a frame count >= 1, got {orbit}")
    if camera_path is not None:
        cameras, path_fps = read_nerfstudio_path(camera_path)
        return cameras, [c.name for c in cameras], fps or path_fps or DEFAULT_FPS
    if orbit:
        if not cameras:
            raise RadfieldError("--orbit circles the dataset's cameras: give --dataset for a model file")
        params = orbit_from_cameras(cameras)
        cameras = make_orbit(params["target"], params["radius"], elevation, orbit, cameras[0], up=params["up"])
        return cameras, [c.name for c in cameras], fps or DEFAULT_FPS
    return cameras, names, fps or DEFAULT_FPS


def render_frames(model_file: Path, run_dir: Path | None, dataset: Path | None, split: str, out_dir: Path, *,
                  options: dict[str, Any] | None = None, device: str | torch.device = "cpu",
                  orbit: int = 0, elevation: float = 20.0, camera_path: Path | None = None,
                  video: Path | None = None, fps: float = 0.0,
                  on_start: Callable[[int], None] | None = None,
                  on_frame: Callable[[], None] | None = None) -> dict[str, Any]:
    """Render `split` of `dataset` (default: the run's) with the model into out_dir/<view>.png.

    `orbit` frames around the split's cameras, or the cameras of the nerfstudio file `camera_path`,
    replace them (path_cameras); `video`: also write the frames as an MP4 at `fps` frames per
    second (0: the camera path's, else DEFAULT_FPS). A model file with a camera path needs no
    dataset; an orbit needs one to circle.

    on_start(number of views) and on_frame() drive a progress bar. Returns views, width, height,
    primitives, kind and ms_per_frame (rendering only, after one untimed warm-up render, the
    device synchronised before each clock reading)."""
    on_path = bool(orbit) or camera_path is not None
    # a run edited from a model file (radfield edit MODEL -o RUN) has no config and no dataset of its own
    run = Run(run_dir) if run_dir is not None else None
    config = run.config(options) if run is not None else load_config(None, options=options or {})
    if dataset is None:
        dataset = run.dataset() if run is not None else None
        if dataset is None and not on_path:
            what = f"{run_dir} (edited from a model file)" if run_dir is not None else "a model file"
            raise RadfieldError(f"--dataset is required to render {what}: a reconstructed run knows its dataset")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise RadfieldError(f"{out_dir}: exists and is not a folder")
    model = load_model(model_file, device=device)
    background, near = tuple(config["data"]["background"]), config["render"]["near"]
    draw = lambda camera: render_model(model, camera, background=background, near=near)  # its own n × n rays a pixel
    cameras, names = [], []
    if dataset is not None:
        data = load_split(dataset, split, config["data"])
        cameras, names = data.cameras, [view.image_path.stem for view in data.views]
    frame_rate = fps or DEFAULT_FPS
    if on_path:
        cameras, names, frame_rate = path_cameras(cameras, names, orbit, elevation, camera_path, fps)
    if on_start is not None:
        on_start(len(cameras))
    with torch.no_grad():  # warm-up, untimed: the first render loads the fused kernels
        draw(cameras[0])
    seconds, frames = 0.0, []
    with atomic_folder(out_dir, merge=True) as tmp:
        for name, camera in zip(names, cameras):
            start = clock(device)
            with torch.no_grad():
                color = draw(camera).color
            seconds += clock(device) - start
            pixels = color.clamp(0, 1).cpu().numpy()
            write_image(tmp / f"{name}.png", pixels)
            if video is not None:
                frames.append((pixels * 255.0 + 0.5).astype("uint8"))
            if on_frame is not None:
                on_frame()
        if video is not None:
            write_video(video, frames, frame_rate)
    first = cameras[0]
    return {"views": len(cameras), "width": first.width, "height": first.height, "primitives": len(model),
            "kind": model.kind, "ms_per_frame": 1e3 * seconds / len(cameras)}
