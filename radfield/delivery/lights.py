"""The lights a relightable model is drawn or exported under (Splat the Net appendix C.2; issue 30):
`--light X,Y,Z`, `--light-dir X,Y,Z`, `--light-intensity K` and `--light-orbit N` of `radfield
render`, `export` and `view`.

A relightable kind (core/kinds/relight.py) draws each view under one known light: render() reads
Camera.light, and `kind.at_light(prims, light)` is the static model of one light. Which kind is
relightable is asked of the kind registry (`conditions`), never branched on by name; a light given
for a model that is not relightable is refused (one line), as a time for a static model is
(delivery/times.py).

The frame: a run's model and its dataset's cameras and lights are in the dataset's own world
frame (training normalises internally and undoes it on save, datasets/scene.py `Normalization`),
so a user's light is taken as it is, in that frame, with the dataset's intensity units (without
--light-intensity: the mean intensity of the dataset's lights, `as_bright_as`). A point
light inside the object's bounds (datasets/bounds.py, the check the data side applies to a
dataset's lights) is one error.

A light orbit circles the object about the dataset's "up" at the mean distance and mean elevation
of the dataset's point lights from the object's centre (their mean intensity), or with directional
lights their mean elevation; the viewer's sliders place a light by the same (azimuth, elevation,
distance) about a centre (`light_at`, `light_angles`).
Light to import (no torch): the CLI checks options with it before loading anything.
"""

from __future__ import annotations

import math
from dataclasses import replace

from radfield.errors import RadfieldError
from radfield.util.numbers import three_numbers


def parse_vector(text: str, option: str) -> tuple[float, float, float]:
    """Three finite numbers X,Y,Z of an option."""
    vector = three_numbers(text)
    if vector is None or not all(math.isfinite(x) for x in vector):
        raise RadfieldError(f"{option} takes three finite numbers X,Y,Z (the dataset's world frame), got {text!r}")
    return vector


def light_from_options(position: str | None, direction: str | None, intensity: float | None):
    """The Light of --light / --light-dir / --light-intensity (None when neither light is given;
    the intensity then only sets a light orbit's, see `orbit_lights`). Without an intensity it is
    1 here, and the dataset's lights' where a dataset is known (`as_bright_as`)."""
    from radfield.core.geometry.cameras import Light

    if position is not None and direction is not None:
        raise RadfieldError("--light (a point light) and --light-dir (a directional light) exclude each other")
    if intensity is not None and not (math.isfinite(intensity) and intensity > 0):
        raise RadfieldError(f"--light-intensity must be a positive number, got {intensity:g}")
    if position is not None:
        return Light(position=parse_vector(position, "--light"), intensity=intensity or 1.0)
    if direction is not None:
        vector = parse_vector(direction, "--light-dir")
        if not any(vector):
            raise RadfieldError("--light-dir must not be 0,0,0 (it is the direction the light shines along)")
        return Light(direction=vector, intensity=intensity or 1.0)
    return None


def as_bright_as(light, lights):
    """`light` with the mean intensity of the dataset's `lights` of its type (point or directional),
    for a light given without --light-intensity: a capture's intensities are in its own units (the
    olat demo scene's are LIGHT_RADIUS² = 7.6), so intensity 1 would draw a relit model nearly
    black. Unchanged when the dataset has no light of that type."""
    if light is None:
        return None
    same = [other.intensity for other in lights
            if other is not None and (other.position is None) == (light.position is None)]
    return replace(light, intensity=sum(same) / len(same)) if same else light


def light_option(light) -> str:
    """The option that gave `light`, for messages."""
    return "--light" if light is None or light.position is not None else "--light-dir"


def is_relightable(model) -> bool:
    """Whether the model's kind draws a view under the view's light (its `conditions` hold "light")."""
    from radfield.core import kinds

    return "light" in kinds.of(model).conditions


def check_takes_light(model, source, option: str = "--light") -> None:
    """A light option given for a model that is not relightable: one error line (not ignored: its
    images would not change with the light)."""
    if not is_relightable(model):
        raise RadfieldError(f"{source}: {option} is for a relightable model; this one ({model.kind}) is not "
                            f"(leave out {option})")


def check_lit(model, source, cameras, what: str) -> None:
    """A relightable model draws every camera under its own light: one error line, before any output
    is written, when some camera has none (an orbit, a camera path, a dataset without lights)."""
    if is_relightable(model) and any(camera.light is None for camera in cameras):
        raise RadfieldError(f"{source}: this model is relightable ({model.kind}): give a light for {what} "
                            "(--light X,Y,Z, --light-dir X,Y,Z or --light-orbit N)")


def dataset_bounds(cameras, dataset):
    """The object's bounds as the data side sees them (datasets/bounds.py: the dataset's mesh.ply,
    else the ball its cameras frame), None without a dataset or when they say nothing."""
    from pathlib import Path

    from radfield.datasets.bounds import MESH, object_bounds

    if dataset is None or not cameras:
        return None
    return object_bounds(list(cameras), Path(dataset) / MESH)


def check_outside(light, bounds, option: str = "--light") -> None:
    """A point light inside the object's bounds lights nothing the cameras see (and usually is a
    light given in other units or another frame): one error line."""
    if light is None or light.position is None or bounds is None:
        return
    if bounds.contains(light.position):
        raise RadfieldError(f"{option} {','.join(f'{x:g}' for x in light.position)} is inside the object's bounds "
                            f"({bounds.describe()}): a point light must be outside the object")


def under(cameras, light) -> list:
    """The cameras lit by `light`."""
    return [replace(camera, light=light) for camera in cameras]


def model_at(model, light):
    """The static model of a relightable one under `light` (its kind's `at_light`, eq. 14)."""
    from radfield.core import kinds

    return kinds.of(model).at_light(model, light)


# --- lights placed about a centre: orbits and the viewer's sliders ---------------------------------------

def _basis(up):
    """Unit (e1, e2, up) of the plane normal to `up` (numpy vectors)."""
    import numpy as np

    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = helper - (helper @ up) * up
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1), up


def light_at(centre, up, azimuth: float, elevation: float, distance: float | None, intensity: float):
    """A point light at `distance` from `centre` in the direction (azimuth, elevation) (degrees;
    elevation above the plane normal to `up`), or with distance None a directional light shining
    from that direction towards the centre."""
    import numpy as np

    from radfield.core.geometry.cameras import Light

    e1, e2, up = _basis(up)
    a, e = math.radians(azimuth), math.radians(elevation)
    towards = math.cos(e) * (math.cos(a) * e1 + math.sin(a) * e2) + math.sin(e) * up
    if distance is None:
        return Light(direction=tuple(float(x) for x in -towards), intensity=intensity)
    return Light(position=tuple(float(x) for x in np.asarray(centre, np.float64) + distance * towards), intensity=intensity)


def light_angles(centre, up, light) -> tuple[float, float, float | None]:
    """(azimuth, elevation, distance) of `light` about `centre` as `light_at` takes them (distance
    None for a directional light)."""
    import numpy as np

    e1, e2, up = _basis(up)
    if light.position is not None:
        offset = np.asarray(light.position, np.float64) - np.asarray(centre, np.float64)
        distance = float(np.linalg.norm(offset))
        towards = offset / max(distance, 1e-12)
    else:
        towards, distance = -np.asarray(light.direction, np.float64), None
    elevation = math.degrees(math.asin(float(np.clip(towards @ up, -1.0, 1.0))))
    azimuth = math.degrees(math.atan2(float(towards @ e2), float(towards @ e1)))
    return azimuth, elevation, distance


def orbit_lights(lights, centre, up, count: int, intensity: float | None = None) -> list:
    """`count` lights circling `centre` about `up` (module docstring): at the mean distance, mean
    elevation and mean intensity (or `intensity`) of the dataset's `lights`, starting at the first
    one's azimuth."""
    if count < 1:
        raise RadfieldError(f"--light-orbit takes a frame count >= 1, got {count}")
    known = [light for light in lights if light is not None]
    if not known:
        raise RadfieldError("--light-orbit circles the dataset's lights: the dataset has none (give --light or "
                            "--light-dir for each view instead)")
    points = [light for light in known if light.position is not None] or known
    angles = [light_angles(centre, up, light) for light in points]
    elevation = sum(e for _, e, _ in angles) / len(angles)
    distance = None if points[0].position is None else sum(d for *_, d in angles) / len(angles)
    power = intensity or sum(light.intensity for light in points) / len(points)
    start = angles[0][0]
    return [light_at(centre, up, start + 360.0 * k / count, elevation, distance, power) for k in range(count)]
