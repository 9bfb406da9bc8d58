"""`radfield render`: draw every camera of a dataset split (or an orbit around them, or a camera
path, or one of its views) with a trained model into a folder of PNGs, and optionally an MP4.

For a run directory every default is the run's own (RUN/config.yaml): the dataset it trained on
(radfield.run.Run.dataset), its split rule (data.test_every), background, downscale and near plane;
`options` ({"data.background": [...], "data.downscale": 2, "render.near": 0.05}) win over them.
A run or a model file is drawn as it was trained: each pixel the mean of the model's own n × n
rays (its `supersample`, core/antialias.render_model).
The frames are written into a temporary folder beside the output and moved into place at the end,
so a failed render leaves no partial output.

A conditioned model (a kind with `conditions`: time-conditioned, core/kinds/dynamic.py; relightable,
core/kinds/relight.py) draws each view under its own value of each condition (Camera.conditions;
radfield/conditions): a dataset's views under their own, or what the options asked (`asked`, one
`conditions.Asked` per condition): one value for every view, or several (condition_frames: one
image per view and value, `<view>_<tag><k>.png`, e.g. `_t0003` for a time and `_l0003` for a light,
or along an orbit or a camera path one value a frame: a time-lapse, a light going round).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from radfield.util.atomic import atomic_folder
from radfield.core.geometry.camera_path import orbit as make_orbit
from radfield.core.geometry.camera_path import orbit_from_cameras, read_nerfstudio_path, write_video
from radfield.core.geometry.cameras import distinct_poses
from radfield.errors import RadfieldError
from radfield.model_formats import load as load_model
from radfield.core.render.antialias import render_model
from radfield.util.timing import clock
from radfield.datasets.images import write_image
from radfield.pipeline.config import load_config, run_config
from radfield.datasets.scene import load_split
from radfield import conditions
from radfield.run import Run

DEFAULT_FPS = 30.0
SEPARATORS = "_-. "   # between the parts of a frame name (r_000_t000)


def path_cameras(cameras, names, orbit: int, elevation: float, camera_path: Path | None, fps: float):
    """The cameras to draw instead of a split's: an orbit of `orbit` frames around `cameras` (at
    `elevation` degrees), or the cameras of a nerfstudio camera-path file. Returns (cameras,
    frame names, fps): `fps`, else the camera path's, else DEFAULT_FPS."""
    if orbit and camera_path is not None:
        raise RadfieldError("--orbit and --camera-path exclude each other")
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


def split_views(data, which: str | None, one_per_pose: bool) -> tuple[list, list[str]]:
    """(cameras, names) of the split `data` to draw: every view, or the one `which` names (its frame
    name or index). `one_per_pose`: the options give every view its moment or light, so the views
    that differ only by theirs (a dynamic dataset's camera at each of its moments) are drawn once,
    named by what their names share (r_000_t000 … r_000_t023: r_000, which `which` may name too),
    not once per recorded moment."""
    cameras, names = data.cameras, data.names
    if not one_per_pose:
        chosen = range(len(cameras)) if which is None else [data.view_index(which)]
        return [cameras[k] for k in chosen], [names[k] for k in chosen]
    poses, pose_of = distinct_poses(cameras)
    groups: dict[int, list[str]] = {}
    for k, pose in enumerate(pose_of):
        groups.setdefault(pose, []).append(names[k])
    pose_names = [shared_name(groups[pose]) for pose in range(len(poses))]
    if len(set(pose_names)) < len(pose_names):   # two poses whose names share the same stem
        pose_names = [groups[pose][0] for pose in range(len(poses))]
    if which is None:
        drawn = range(len(poses))
    else:
        drawn = [pose_names.index(which) if which in pose_names else pose_of[data.view_index(which)]]
    return [poses[p] for p in drawn], [pose_names[p] for p in drawn]


def shared_name(names: list[str]) -> str:
    """What frame names share up to a separator: r_000_t000, r_000_t001 -> r_000 (one name: itself)."""
    prefix = os.path.commonprefix(names)
    if len(names) > 1 and not all(len(name) == len(prefix) or name[len(prefix)] in SEPARATORS for name in names):
        prefix = prefix[:max(prefix.rfind(c) for c in SEPARATORS) + 1]   # back to the last whole part
    return prefix.rstrip(SEPARATORS) or names[0]


def condition_frames(cameras, names, condition: conditions.Condition, asked: conditions.Asked, path: str | None):
    """The (cameras, names) to draw under what the options asked of `condition` (module docstring):
    one value for every camera; several along an orbit or a camera path (`path` names it) paired
    with its frames one to one (both move), else every camera at every value, `<name>_<tag><k>`."""
    if not asked.several:
        return [camera.at(**{condition.name: asked.value}) for camera in cameras], names
    values = asked.values
    suffixes = [f"_{condition.tag}{k:04d}" for k in range(len(values))]
    if path is not None:
        if len(values) != len(cameras):
            raise RadfieldError(f"{asked.option} gives {len(values)} {condition.unit} but {path} has {len(cameras)} "
                                f"frames: {condition.pairing} (give as many)")
        return ([c.at(**{condition.name: v}) for c, v in zip(cameras, values)],
                [name + suffix for name, suffix in zip(names, suffixes)])
    return ([c.at(**{condition.name: v}) for c in cameras for v in values],
            [name + suffix for name in names for suffix in suffixes])


def dataset_bounds(cameras, dataset):
    """The object's bounds as the data side sees them (datasets/bounds.py: the dataset's mesh.ply,
    else the ball its cameras frame), None without a dataset or when they say nothing."""
    from radfield.datasets.bounds import MESH, object_bounds

    if dataset is None or not cameras:
        return None
    return object_bounds(list(cameras), Path(dataset) / MESH)


def render_frames(model_file: Path, run_dir: Path | None, dataset: Path | None, split: str, out_dir: Path, *,
                  options: dict[str, Any] | None = None, device: str | torch.device = "cpu",
                  orbit: int = 0, elevation: float = 20.0, camera_path: Path | None = None,
                  video: Path | None = None, fps: float = 0.0, camera: str | None = None,
                  asked: dict[str, conditions.Asked] | None = None,
                  on_start: Callable[[int], None] | None = None,
                  on_frame: Callable[[], None] | None = None) -> dict[str, Any]:
    """Render `split` of `dataset` (default: the run's) with the model into out_dir/<view>.png.

    `orbit` frames around the split's cameras, or the cameras of the nerfstudio file `camera_path`,
    replace them (path_cameras); `video`: also write the frames as an MP4 at `fps` frames per
    second (0: the camera path's, else DEFAULT_FPS). A model file with a camera path needs no
    dataset; an orbit needs one to circle. `camera`: only the split's view of that name (or index),
    e.g. the fixed camera of a time-lapse.

    A conditioned model: `asked` (condition name -> what the options asked, conditions.Asked, each
    resolved against the split's views: a light as bright as the dataset's, a light orbit about the
    object), else each view's own values (the dataset's); a camera without a value, a value for a
    model whose kind does not read that condition, or a point light inside the object's bounds is
    one error before anything is written (radfield/conditions). A value given for every view draws
    each camera pose of the split once (split_views).

    on_start(number of images) and on_frame() drive a progress bar. Returns images, views (the
    distinct camera poses drawn), width, height, primitives, kind, drawn_under (condition name -> the
    number of its distinct values drawn, for each condition the model's kind reads) and ms_per_frame
    (rendering only, after one untimed warm-up render, the device synchronised before each clock
    reading)."""
    on_path = bool(orbit) or camera_path is not None
    if camera is not None and on_path:
        raise RadfieldError(f"--camera and --{'orbit' if orbit else 'camera-path'} exclude each other")
    asked = {name: asked[name] for name in conditions.names() if name in (asked or {})}   # registration order
    # a run edited from a model file (radfield edit MODEL -o RUN) has no config and no dataset of its own
    run = Run(run_dir) if run_dir is not None else None
    config = run_config(run, options) if run is not None else load_config(None, options=options or {})
    if dataset is None:
        dataset = run.dataset() if run is not None else None
        if dataset is None and (not on_path or camera is not None):
            what = f"{run_dir} (edited from a model file)" if run_dir is not None else "a model file"
            raise RadfieldError(f"--dataset is required to render {what}: a reconstructed run knows its dataset")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise RadfieldError(f"{out_dir}: exists and is not a folder")
    model = load_model(model_file, device=device)
    for name, request in asked.items():
        conditions.check_takes(model, model_file, name, request.option)
    background, near = tuple(config["data"]["background"]), config["render"]["near"]
    draw = lambda camera: render_model(model, camera, background=background, near=near)  # its own n × n rays a pixel
    # every view given its moment or light by the options: one image per pose, not per recorded one
    one_per_pose = bool(asked)
    cameras, names, recorded = [], [], []   # recorded: the split's views with their own conditions
    if dataset is not None:
        data = load_split(dataset, split, config["data"])
        cameras, names = split_views(data, camera, one_per_pose)
        recorded = data.cameras
    bounds = functools.cache(lambda: dataset_bounds(recorded, dataset))
    asked = {name: conditions.get(name).resolved(request, recorded, bounds) for name, request in asked.items()}
    frame_rate = fps or DEFAULT_FPS
    if on_path:
        cameras, names, frame_rate = path_cameras(cameras, names, orbit, elevation, camera_path, fps)
    path = "the orbit" if orbit else f"the camera path {camera_path}" if camera_path is not None else None
    for name, request in asked.items():
        cameras, names = condition_frames(cameras, names, conditions.get(name), request, path)
    conditions.check_given(model, model_file, cameras, path or f"the {split} views of {dataset}")
    if on_start is not None:
        on_start(len(cameras))
    with torch.no_grad():  # warm-up, untimed: the first render loads the fused kernels
        draw(cameras[0])
    seconds, frames = 0.0, []
    with atomic_folder(out_dir, merge=True) as tmp:
        for name, view in zip(names, cameras):
            start = clock(device)
            with torch.no_grad():
                color = draw(view).color
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
    drawn_under = {c.name: len({c.key(view.conditions[c.name]) for view in cameras}) for c in conditions.taken(model)}
    return {"images": len(cameras), "views": len(distinct_poses(cameras)[0]), "width": first.width,
            "height": first.height, "primitives": len(model), "kind": model.kind,
            "ms_per_frame": 1e3 * seconds / len(cameras), "drawn_under": drawn_under}
