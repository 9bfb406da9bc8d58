"""`radfield render`: draw every camera of a dataset split with a trained model into a folder of PNGs.

For a run directory every default is the run's own (RUN/config.yaml): the dataset it trained on
(stages.info.run_dataset), its split rule (data.test_every), background, downscale and near plane;
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
from radfield.core.geometry.camera_path import write_video
from radfield.errors import RadfieldError
from radfield.delivery.io import load_model
from radfield.core.render.antialias import render_model
from radfield.util.timing import clock
from radfield.datasets.images import write_image
from radfield.pipeline.config import load_config
from radfield.datasets.scene import load_split
from radfield.pipeline.info import run_dataset
from radfield.pipeline.runner import CONFIG_FILE


def render_frames(model_file: Path, run_dir: Path | None, dataset: Path | None, split: str, out_dir: Path, *,
                  options: dict[str, Any] | None = None, device: str | torch.device = "cpu",
                  camera_path: Callable[[list, list[str]], tuple[list, list[str]]] | None = None,
                  video: Path | None = None, fps: Callable[[], float] = lambda: 30.0,
                  on_start: Callable[[int], None] | None = None,
                  on_frame: Callable[[], None] | None = None) -> dict[str, Any]:
    """Render `split` of `dataset` (default: the run's) with the model into out_dir/<view>.png.

    camera_path(cameras, names) -> (cameras, names) replaces the split's cameras (an orbit around
    them, a camera-path file); `video`: also write the frames as an MP4 at fps() frames per second.
    A model file with a camera path needs no dataset: camera_path then gets no cameras, and must
    bring its own (a camera-path file) or fail with a RadfieldError (an orbit).

    on_start(number of views) and on_frame() drive a progress bar. Returns views, width, height,
    primitives, kind and ms_per_frame (rendering only, after one untimed warm-up render, the
    device synchronised before each clock reading)."""
    # a run edited from a model file (radfield edit MODEL -o RUN) has no config and no dataset of its own
    config_file = Path(run_dir) / CONFIG_FILE if run_dir is not None else None
    config = load_config(config_file if config_file is not None and config_file.is_file() else None,
                         options=options or {})
    if dataset is None:
        dataset = run_dataset(run_dir) if run_dir is not None else None
        if dataset is None and camera_path is None:
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
    if camera_path is not None:
        cameras, names = camera_path(cameras, names)
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
            write_video(video, frames, fps())
    first = cameras[0]
    return {"views": len(cameras), "width": first.width, "height": first.height, "primitives": len(model),
            "kind": model.kind, "ms_per_frame": 1e3 * seconds / len(cameras)}
