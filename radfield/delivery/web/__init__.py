"""The browser renderer's folder (`radfield export RUN -f web -o DIR`, served by `radfield view`):
a static site that draws the model on the viewer's own GPU with WebGL2, as `render()` draws it.

    DIR/index.html, *.js   the page and its renderer (assets/: plain ES modules, no build step)
    DIR/view.json          the cameras by split, background, orbit centre and up, conditions' starts
    DIR/model.bin          the model (model_bin.py: float16 where that costs nothing measurable)

The page and the two files' layout are documented in docs/formats.md ("The web export"); this
module writes them from what a viewer shows (delivery/view_scene.py: ViewerScene).
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import torch

from radfield import conditions
from radfield.core.geometry.camera_path import orbit
from radfield.core.geometry.cameras import Camera
from radfield.core.render.antialias import render_model
from radfield.core.train.losses import psnr
from radfield.delivery.view_scene import ViewerScene
from radfield.delivery.web import model_bin
from radfield.util.atomic import atomic_write_bytes, atomic_write_text

ASSETS = Path(__file__).parent / "assets"
FIDELITY_VIEWS = 3           # cameras the compact model is checked at (test views first)
ORBIT_VIEWS = 8              # a model file's cameras: a turntable at 20 degrees
ORBIT_SIZE = 512
LIGHT_DISTANCES = (0.25, 4.0)   # the light distance slider's range, times the start light's distance


def write_site(scene: ViewerScene, out: Path, title: str = "radfield", check: bool = True) -> dict:
    """Write the web folder of `scene` into the folder `out` (created if missing; files of the same
    names replaced). Returns the export line's figures: primitives, precision, bytes, and how close
    the page's numbers render to the float32 model (at FIDELITY_VIEWS cameras; `check` False: not
    measured, the compact precision kept, for benchmarks)."""
    out.mkdir(parents=True, exist_ok=True)
    document = view_document(scene, title)
    compact = model_bin.encode(scene.model, compact=True)
    closeness = min((psnr_of(scene, model_bin.decoded(scene.model, compact), camera)
                     for camera in fidelity_cameras(scene)), default=math.inf) if check else math.inf
    keep = closeness >= model_bin.HALF_MIN_PSNR
    blob = compact if keep else model_bin.encode(scene.model, compact=False)
    for asset in sorted(ASSETS.iterdir()):
        if asset.is_file():
            shutil.copyfile(asset, out / asset.name)
    atomic_write_bytes(out / "model.bin", blob)
    atomic_write_text(out / "view.json", json.dumps(document, separators=(",", ":")) + "\n")
    how = "float16" if keep else "float32"
    return {"primitives": len(scene.model), "precision": how, "model.bin": f"{len(blob) / 1e6:.2f} MB",
            "float16 render": f"{closeness:.1f} dB against float32" + ("" if keep else
                                                                       f" (below {model_bin.HALF_MIN_PSNR} dB)")}


def psnr_of(scene: ViewerScene, other, camera: Camera) -> float:
    """PSNR (dB) of `other`'s render against the scene's model's at `camera`."""
    with torch.no_grad():
        a = render_model(scene.model, camera, background=scene.background, near=scene.near).color.clamp(0, 1)
        b = render_model(other, camera, background=scene.background, near=scene.near).color.clamp(0, 1)
    return float(psnr(b, a))


def fidelity_cameras(scene: ViewerScene) -> list[Camera]:
    """Up to FIDELITY_VIEWS cameras (test, else train, else orbit), at the conditions' starts."""
    cameras = scene.splits.get("test") or scene.splits.get("train") or orbit_cameras(scene)
    values = start_values(scene)
    return [camera.at(**values) for camera in cameras[:FIDELITY_VIEWS]]


def start_values(scene: ViewerScene) -> dict:
    """The value of each condition the model takes where the page starts."""
    taken = {condition.name for condition in conditions.taken(scene.model)}
    return {**({"time": scene.time} if "time" in taken else {}),
            **({"light": scene.start_light()} if "light" in taken else {})}


def orbit_cameras(scene: ViewerScene) -> list[Camera]:
    """A model file's cameras: ORBIT_VIEWS around its centre at three times its spread, 50 degrees
    of vertical field of view."""
    focal = 0.5 * ORBIT_SIZE / math.tan(math.radians(25.0))
    template = Camera(focal, focal, ORBIT_SIZE / 2, ORBIT_SIZE / 2, ORBIT_SIZE, ORBIT_SIZE, torch.eye(4))
    return orbit(scene.centre, 3.0 * scene.spread, 20.0, ORBIT_VIEWS, template, up=tuple(scene.up))


def view_document(scene: ViewerScene, title: str) -> dict:
    """view.json (docs/formats.md): cameras by split (a model file's: an orbit), background, the
    orbit's centre and up, the model's size, the camera the page opens at, the conditions' starts."""
    splits = {split: [camera_entry(c) for c in cameras] for split, cameras in scene.splits.items() if cameras}
    if not splits:
        splits = {"orbit": [camera_entry(c) for c in orbit_cameras(scene)]}
    start = next(f"{split}:0" for split in ("test", "train", "orbit", *splits) if split in splits)
    document = {"format": model_bin.FORMAT, "version": model_bin.VERSION, "model": "model.bin", "title": title,
                "kind": scene.model.kind, "primitives": len(scene.model),
                "background": [float(x) for x in scene.background], "near": scene.near, "centre": _floats(scene.centre),
                "up": _floats(scene.up), "radius": 3.0 * scene.spread, "cameras": splits, "start": start,
                "conditions": {}}
    values = start_values(scene)
    if "time" in values:
        document["conditions"]["time"] = {"start": float(values["time"])}
    if "light" in values:
        light = values["light"]
        distance = (float(np.linalg.norm(np.asarray(light.position) - scene.centre)) if light.position is not None
                    else 3.0 * scene.spread)
        document["conditions"]["light"] = {"start": light_entry(light),
                                           "distances": [distance * f for f in LIGHT_DISTANCES]}
    return document


def camera_entry(camera: Camera) -> dict:
    """One camera of view.json: intrinsics, size, camera-to-world (OpenCV axes), its conditions."""
    entry = {"name": camera.name, "width": camera.width, "height": camera.height, "fx": camera.fx, "fy": camera.fy,
             "cx": camera.cx, "cy": camera.cy, "c2w": camera.c2w.tolist()}
    if "time" in camera.conditions:
        entry["time"] = float(camera.conditions["time"])
    if "light" in camera.conditions:
        entry["light"] = light_entry(camera.conditions["light"])
    return entry


def light_entry(light) -> dict:
    where = {"position": list(light.position)} if light.position is not None else {"direction": list(light.direction)}
    return {**where, "intensity": float(light.intensity)}


def _floats(values) -> list[float]:
    return [float(x) for x in values]
