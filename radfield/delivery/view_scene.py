"""What a viewer shows of a run or a model file (`radfield view`, both the browser renderer of
`radfield export -f web` (delivery/web/) and the server-rendered viewer (delivery/viewer.py)): the
model, the run's cage, the dataset's cameras by split, the background, and where a conditioned
model starts (its first moment, its first light)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from radfield import conditions
from radfield.conditions.light import light_at, orbit_lights
from radfield.core.geometry.cameras import Camera
from radfield.delivery.export import view_cameras


@dataclass
class ViewerScene:
    """What the viewer shows: primitives (on `device`), and optionally the cage (V, 3) + (T, 4) and
    the dataset cameras (radfield Cameras, one a pose; `splits`: every view by split, train first).
    `time`: the moment a dynamic model is first shown;
    `light`: the light a relightable model is first drawn under (None for other models); `lights`:
    the dataset views' lights (a relighting dataset's; where the default light comes from)."""

    model: object
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    cage: tuple[np.ndarray, np.ndarray] | None = None
    cameras: list[Camera] = field(default_factory=list)
    time: float = 0.0
    light: object = None
    lights: list = field(default_factory=list)
    splits: dict[str, list[Camera]] = field(default_factory=dict)
    near: float = 0.01     # the near plane (a run's render.near)

    @property
    def centre(self) -> np.ndarray:
        """The model's centre (the median of its means): the orbit's target."""
        return self.model.means.detach().median(0).values.cpu().double().numpy()

    @property
    def spread(self) -> float:
        """The model's size: the norm of its means' standard deviations (at least 1e-3)."""
        return max(float(self.model.means.detach().std(0).norm().cpu()), 1e-3) if len(self.model) > 1 else 1.0

    @property
    def up(self) -> np.ndarray:
        return dataset_up(self.cameras)

    def start_light(self):
        """A relightable model's first light: `light` (--light), else the first of the dataset's
        lights' orbit (their mean distance and elevation), else (a model file) 45 degrees up at three
        times the model's spread, of intensity distance², which lights the centre with irradiance 1
        as the olat demo scene's lights do."""
        if self.light is not None:
            return self.light
        if self.lights:
            return orbit_lights(self.lights, self.centre, self.up, 1)[0]
        distance = 3.0 * self.spread
        return light_at(self.centre, self.up, 0.0, 45.0, distance, distance**2)


def viewer_scene(target, device: str = "cpu", background: tuple[float, float, float] | None = None,
                 asked: dict[str, conditions.Asked] | None = None) -> ViewerScene:
    """What `radfield view TARGET` shows: the model of a model file or a run, and for a run its cage
    and its dataset's cameras. An edited run has no data stage of its own: its cameras (and
    background) are its source run's (radfield.run.Run.dataset_scene), since an edit keeps the
    world frame. `background` overrides the run's (default white). `asked` (condition name ->
    conditions.Asked): a dynamic model's first moment (default 0), a relightable model's first
    light (default: module docstring), each resolved against the dataset's views (a light as bright
    as the dataset's lights unless its intensity was given); a value for a model whose kind does not
    read that condition, or a point light inside the run's object bounds, is one error."""
    import functools
    from pathlib import Path

    from radfield.datasets.scene import load_scene
    from radfield.delivery.content import load_content, run_bounds
    from radfield.pipeline.config import run_config
    from radfield.run import Run, is_run_dir

    asked = asked or {}
    content = load_content(Path(target), device, parts=("cage", "cameras"))
    for name, request in asked.items():
        conditions.check_takes(content.model, target, name, request.option)
    views, run_background = content.views, content.background
    if views is None and is_run_dir(target):
        scene_file = Run(target).dataset_scene()
        if scene_file is not None:
            scene = load_scene(scene_file)
            run_background = run_background or scene.background
            views = scene.splits if scene.posed else None
    recorded = view_cameras([v for split in (views or {}).values() for v in split])
    bounds = functools.cache(lambda: run_bounds(content))
    values = {name: conditions.get(name).resolved(request, recorded, bounds).value for name, request in asked.items()}
    lights = [camera.conditions["light"] for camera in recorded if "light" in camera.conditions]
    splits = {split: view_cameras(views[split]) for split in sorted(views or {}, key=lambda s: s != "train")}
    near = run_config(Run(target))["render"]["near"] if is_run_dir(target) else 0.01
    return ViewerScene(content.model, background or run_background or (1.0, 1.0, 1.0), content.cage,
                       viewer_cameras(views), values.get("time") or 0.0, values.get("light"), lights, splits, near)


def viewer_cameras(splits: dict[str, list[dict]] | None) -> list[Camera]:
    """radfield Cameras of scene.json views (every split; the train views first), one a pose: a
    dynamic dataset's camera photographs many moments from the same place."""
    cameras = view_cameras([v for split in sorted(splits or {}, key=lambda s: s != "train") for v in splits[split]])
    poses = {}
    for camera in cameras:
        poses.setdefault(camera.c2w.numpy().tobytes(), camera)
    return list(poses.values())


def dataset_up(cameras: list[Camera]) -> np.ndarray:
    """The dataset's mean "up" (−y of each camera, OpenCV axes), unit; +z without cameras."""
    if not cameras:
        return np.array([0.0, 0.0, 1.0])
    up = -np.mean([c.c2w[:3, 1].numpy() for c in cameras], axis=0)
    return up / max(np.linalg.norm(up), 1e-12)
