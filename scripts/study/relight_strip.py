"""The relighting strip of docs/usage.md ("Relighting"; issue 30): one held-out camera of an `olat`
run under N point lights circling the object, the exact truth above and the run's model below,
each pair's PSNR printed and written under it.

    usage: OMP_NUM_THREADS=1 .venv/bin/python scripts/study/relight_strip.py RUN
               [--out docs/images/relight-strip.png] [--camera 5] [--lights 8] [--elevation 40]
               [--full-frame] [--no-psnr]

RUN is a run of `radfield demo-scene olat` (or another OLAT demo scene: the dataset's scene.json
names it); its dataset is the run's input. The camera is the K-th distinct camera of the test
split (the olat scene photographs each test camera under several lights), or the camera of a
test frame named K. The lights: N point lights evenly round the cameras' up axis at `--elevation`
degrees, about the cameras' focus (the object's centre), at the mean distance and with the mean
intensity of the dataset's point lights, the first one at the camera's azimuth (behind the
camera), the N/2-th behind the object: lights the model never saw (each one's angle to the
nearest training light is printed). The truth is the OLAT scene ray traced under that light as
the dataset was (demo/olat.olat_scene, demo/raytrace.render_view with a PointLight, the camera's
own jitter pattern; the script first re-traces one of the camera's test frames and prints its PSNR
against the photo, ~65 dB: 8-bit rounding only), composited on the dataset's background; the
render is the model drawn as `radfield render --light` draws it (delivery/lights.under,
core/render/antialias.render_model: the model's own n × n rays a pixel). PSNR as eval measures it
(evaluation/metrics.psnr), over the whole frame; the picture is cropped to the object (2 px round
it) and upscaled 3× (nearest). Defaults: camera 5 (seen from 47° above, the plinth's top in view)
and elevation 40°: the shadows sweep over the plinth and the highlight round the red sphere. A
study script: not part of the product.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

from radfield.core.geometry.camera_path import orbit_from_cameras
from radfield.core.render.antialias import render_model
from radfield.demo import olat, raytrace, scenes
from radfield.datasets.images import write_image
from radfield.delivery import lights as lighting
from radfield.model_file import load_model
from radfield.evaluation.metrics import psnr
from radfield.errors import RadfieldError
from radfield.evaluation.evaluate import resolve_target

SCALE = 3            # nearest-neighbour upscaling of the strip
MARGIN = 2           # pixels kept round the object when cropping to it
TRUTH_CHECK = 45.0   # dB: below it the re-traced truth is not the dataset's scene (8-bit rounding: ~65 dB)
CAPTION = 7          # pixels of a PSNR caption row (before upscaling)
GAP = 1              # white pixels between panels (before upscaling)


def distinct_cameras(cameras) -> list[list]:
    """The split's views grouped by camera (same pose and intrinsics), in the order they appear."""
    groups: dict[tuple, list] = {}
    for camera in cameras:
        key = (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
               tuple(np.round(camera.c2w.numpy().ravel(), 9)))
        groups.setdefault(key, []).append(camera)
    return list(groups.values())


def pick_camera(cameras, which: str):
    """The `which`-th distinct camera (an index) or the camera of the frame named `which`."""
    groups = distinct_cameras(cameras)
    if which.lstrip("-").isdigit():
        index = int(which)
        if not 0 <= index < len(groups):
            sys.exit(f"relight_strip: --camera {which}: the test split has {len(groups)} cameras (0 … {len(groups) - 1})")
        return index, groups[index][0]
    for index, group in enumerate(groups):
        if any(camera.name == which for camera in group):
            return index, group[0]
    sys.exit(f"relight_strip: --camera {which}: no test frame of that name")


def circle_of_lights(scene, camera, count: int, elevation: float):
    """`count` point lights evenly round the cameras' up at `elevation` degrees (module docstring)."""
    frame = orbit_from_cameras(scene.cameras("train") + scene.cameras("test"))
    known = [light for light in scene.lights("train") if light is not None and light.position is not None]
    if not known:
        sys.exit("relight_strip: the run's dataset has no point lights (an olat run is needed)")
    centre, up = frame["target"], frame["up"]
    distance = float(np.mean([np.linalg.norm(np.asarray(light.position) - centre) for light in known]))
    intensity = float(np.mean([light.intensity for light in known]))
    start, _, _ = lighting.light_angles(centre, up, _towards(camera, centre))
    return [lighting.light_at(centre, up, start + 360.0 * k / count, elevation, distance, intensity)
            for k in range(count)], known, centre


def _towards(camera, centre):
    """A point 'light' at the camera's centre, to read the camera's azimuth with light_angles."""
    from radfield.core.geometry.cameras import Light

    position = camera.c2w[:3, 3].numpy()
    if np.allclose(position, centre):
        return Light(position=tuple(centre + np.array([1.0, 0.0, 0.0])))
    return Light(position=tuple(float(x) for x in position))


def nearest_angle(light, known, centre) -> float:
    """Degrees between `light` and the nearest training light, seen from the centre."""
    ray = np.asarray(light.position) - centre
    others = np.stack([np.asarray(k.position) for k in known]) - centre
    cosines = others @ ray / (np.linalg.norm(others, axis=1) * np.linalg.norm(ray))
    return math.degrees(math.acos(float(np.clip(cosines.max(), -1.0, 1.0))))


def olat_of(scene):
    """(the OLAT scene the run's dataset was generated from, its seed): its scene.json's name and seed."""
    try:
        described = json.loads((Path(scene.root) / "scene.json").read_text())
        return olat.olat_scene(described["name"]), int(described.get("seed", 0))
    except (OSError, ValueError, KeyError, TypeError, RadfieldError):
        sys.exit(f"relight_strip: {scene.root} is not an OLAT demo scene (radfield demo-scene olat)")


def truth(source, camera, light, background, index: int) -> tuple[np.ndarray, np.ndarray]:
    """The OLAT scene (`source`: (scene, seed)) under `light`, ray traced as the dataset was (its
    sampler, the test camera's own jitter pattern, demo/olat._write_split), composited on
    `background`: (H, W, 3), and the coverage (H, W)."""
    shapes, seed = source
    rng = np.random.default_rng([seed, 1, index])
    rgba, _ = raytrace.render_view(shapes, camera, rng=rng,
                                    point_light=scenes.PointLight(tuple(light.position), light.intensity))
    return rgba[..., :3] + (1.0 - rgba[..., 3:]) * np.asarray(background, np.float32), rgba[..., 3]


def check_truth(source, scene, camera, index: int) -> float:
    """PSNR of the truth under the camera's own first test light against that frame's photo: the
    truth is the dataset's scene only if this is high (8-bit rounding alone: ~65 dB)."""
    names = [c.name for c in scene.cameras("test")]
    photo = scene.load_images("test")[0][names.index(camera.name)]
    return float(psnr(torch.from_numpy(truth(source, camera, camera.light, scene.background, index)[0]).float(), photo))


def object_box(coverage: np.ndarray, margin: int = MARGIN) -> tuple[slice, slice]:
    """The rows and columns the object covers (the truth's coverage > 1 %), `margin` pixels wider:
    the strip shows the object, not the empty frame round it (PSNR is of the whole frame)."""
    rows, columns = np.flatnonzero(coverage.max(1) > 0.01), np.flatnonzero(coverage.max(0) > 0.01)
    if not len(rows):
        return slice(None), slice(None)
    height, width = coverage.shape
    return (slice(max(rows[0] - margin, 0), min(rows[-1] + 1 + margin, height)),
            slice(max(columns[0] - margin, 0), min(columns[-1] + 1 + margin, width)))


def captioned(image: np.ndarray, text: str) -> np.ndarray:
    """`image` with a white row below it holding `text` (upscaled first, so the text stays sharp)."""
    import cv2

    row = np.full((CAPTION * SCALE, image.shape[1], 3), 255, np.uint8)
    cv2.putText(row, text, (3, CAPTION * SCALE - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([image, row.astype(np.float32) / 255.0], axis=0)


def strip(truths, renders, psnrs, with_psnr: bool) -> np.ndarray:
    """Truth row above render row, panels upscaled SCALE× (nearest) with white gaps."""
    up = lambda img: np.repeat(np.repeat(np.asarray(img, np.float32), SCALE, 0), SCALE, 1)
    columns = []
    for top, bottom, value in zip(truths, renders, psnrs):
        gap = np.ones((GAP * SCALE, top.shape[1] * SCALE, 3), np.float32)
        column = np.concatenate([up(top), gap, up(bottom)], axis=0)
        columns.append(captioned(column, f"{value:.1f} dB") if with_psnr else column)
    sep = np.ones((columns[0].shape[0], GAP * SCALE, 3), np.float32)
    out = [columns[0]]
    for column in columns[1:]:
        out += [sep, column]
    return np.concatenate(out, axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--out", type=Path, default=Path("docs/images/relight-strip.png"))
    parser.add_argument("--camera", default="5", help="index of a distinct test camera, or a test frame name")
    parser.add_argument("--lights", type=int, default=8)
    parser.add_argument("--elevation", type=float, default=40.0, help="degrees above the plane normal to up")
    parser.add_argument("--full-frame", action="store_true", help="the whole frame, not cropped to the object")
    parser.add_argument("--no-psnr", action="store_true", help="leave the PSNR captions out of the picture")
    args = parser.parse_args()

    model_file, scene, _, config = resolve_target(args.run, None)
    model = load_model(model_file)
    source = olat_of(scene)
    index, camera = pick_camera(scene.cameras("test"), args.camera)
    lights, known, centre = circle_of_lights(scene, camera, args.lights, args.elevation)
    agreement = check_truth(source, scene, camera, index)
    print(f"truth check: camera {index}'s first test frame re-traced against its photo: {agreement:.1f} dB")
    if agreement < TRUTH_CHECK:
        sys.exit(f"relight_strip: the re-traced truth differs from the dataset's photo ({agreement:.1f} dB < "
                 f"{TRUTH_CHECK} dB): the dataset was made by another version of the OLAT scene")
    truths, renders, psnrs = [], [], []
    for k, light in enumerate(lights):
        lit = lighting.under([camera], light)[0]
        with torch.no_grad():
            color = render_model(model, lit, background=scene.background, near=config["render"]["near"]).color
        render = color.clamp(0, 1).cpu()
        image, coverage = truth(source, camera, light, scene.background, index)
        exact = torch.from_numpy(image).float()
        psnrs.append(float(psnr(render, exact)))
        truths.append(exact.numpy())
        renders.append(render.numpy())
        print(f"light {k}: at {', '.join(f'{x:.2f}' for x in light.position)} (nearest training light "
              f"{nearest_angle(light, known, centre):.1f}°): PSNR {psnrs[-1]:.2f} dB")
    print(f"camera {index} ({camera.name}), {args.lights} lights at {args.elevation:g}°: "
          f"mean PSNR {np.mean(psnrs):.2f} dB ({min(psnrs):.2f} … {max(psnrs):.2f})")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if not args.full_frame:
        box = object_box(coverage)
        truths, renders = [t[box] for t in truths], [r[box] for r in renders]
    write_image(args.out, strip(truths, renders, psnrs, not args.no_psnr))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    try:
        main()
    except RadfieldError as error:   # a bad RUN: one line, as the product says it
        sys.exit(f"relight_strip: {error}")
