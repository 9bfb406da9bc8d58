"""Light: the one known light a view is lit by (Splat the Net appendix C.2; issue 30).

A one-light-at-a-time capture (GS³, Kang et al.) gives each transforms.json frame the light it was
lit by: `light_position` ([x, y, z], a point light in the world frame of `transform_matrix`) or
`light_direction` ([x, y, z], a directional light, pointing from the light towards the scene), and
optionally `light_intensity` (> 0, default 1). In scene.json a VIEW's "light" is
{"position" | "direction": [x, y, z], "intensity": k}. Every frame carries a light or none does,
and a point light may not sit inside the object's bounds (datasets/bounds.py): a light inside the
object lights nothing the cameras see, and a light given in the wrong units or frame usually lands
there. The relightable kinds (core/kinds/relight.py) read Camera.conditions["light"] and fix it
(`at_light`, eq. 14).

`radfield render`, `export` and `view` take `--light X,Y,Z`, `--light-dir X,Y,Z` and
`--light-intensity K`; render also `--light-orbit N`. The frame: a run's model and its dataset's
cameras and lights are in the dataset's own world frame (training normalises internally and undoes
it on save), so a user's light is taken as it is, in that frame, with the dataset's intensity units
(without --light-intensity: the mean intensity of the dataset's lights, `as_bright_as`). A light
orbit circles the object about the dataset's "up" at the mean distance and mean elevation of the
dataset's point lights from the object's centre (their mean intensity), or with directional lights
their mean elevation; the viewer's sliders place a light by the same (azimuth, elevation,
distance) about a centre (`light_at`, `light_angles`).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Annotated, Any, Optional

from radfield.conditions.base import Asked, Condition
from radfield.conditions.registry import register
from radfield.errors import RadfieldError
from radfield.util.numbers import three_numbers

_FRAME_KEYS = ("light_position", "light_direction")  # a frame's light is one of these (+ light_intensity)


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


def check_outside(light, bounds, option: str = "--light") -> None:
    """A point light inside the object's bounds lights nothing the cameras see (and usually is a
    light given in other units or another frame): one error line."""
    if light is None or light.position is None or bounds is None:
        return
    if bounds.contains(light.position):
        raise RadfieldError(f"{option} {','.join(f'{x:g}' for x in light.position)} is inside the object's bounds "
                            f"({bounds.describe()}): a point light must be outside the object")


def _number(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)


_HELP = {
    "render": {
        "light": "A relightable model: draw every view under a point light at X,Y,Z (the dataset's world frame; default: each dataset view under its own light).",
        "light_dir": "A relightable model: a directional light shining along X,Y,Z instead.",
        "light_intensity": "The intensity of --light/--light-dir/--light-orbit (a point light's irradiance is K/r²; default: the mean of the dataset's lights, else 1).",
    },
    "export": {
        "light": "A relightable model: ply-3dgs, splat and points under a point light at X,Y,Z (the dataset's world frame; a static model of that lighting; a light is required for a relightable model).",
        "light_dir": "A relightable model: under a directional light shining along X,Y,Z instead.",
        "light_intensity": "The intensity of --light/--light-dir (a point light's irradiance is K/r²; default: the mean of the run's dataset lights, else 1).",
    },
    "view": {
        "light": "A relightable model: the point light it is first drawn under (the dataset's world frame; the light sliders move it; default: where the dataset's lights are).",
        "light_dir": "A relightable model: start with a directional light shining along X,Y,Z instead.",
        "light_intensity": "The intensity of --light/--light-dir (default: the mean of the run's dataset lights, else 1).",
    },
}


class LightCondition(Condition):
    name, plural, unit, model_words, kind_words = "light", "lights", "lights", "relightable", "relightable"
    value_words, how, tag = "a light", "--light X,Y,Z, --light-dir X,Y,Z or --light-orbit N", "l"

    frame_words = ("a light", "no light")
    frame_hint = "give every frame a 'light_position' or 'light_direction', or none"
    drawn, pairing = ("under", "light"), "the light and the camera move together, one light a frame"
    once, how_once = "one lighting", "--light X,Y,Z or --light-dir X,Y,Z"

    # --- reading ------------------------------------------------------------------------------------

    def in_frame(self, frame: dict[str, Any]) -> bool:
        return any(key in frame for key in _FRAME_KEYS)

    def read_frame(self, frame: dict[str, Any], where: str):
        from radfield.core.geometry.cameras import Light

        given = [key for key in _FRAME_KEYS if key in frame]
        if not given:
            if "light_intensity" in frame:
                raise RadfieldError(f"{where}: 'light_intensity' without a 'light_position' or 'light_direction'")
            return None
        if len(given) == 2:
            raise RadfieldError(f"{where}: a light has a 'light_position' (a point light) or a 'light_direction' "
                                "(a directional one), not both")
        key = given[0]
        vector = frame[key]
        if not (isinstance(vector, list) and len(vector) == 3 and all(_number(x) for x in vector)):
            raise RadfieldError(f"{where}: '{key}' must be three finite numbers [x, y, z], not {vector!r:.60}")
        if key == "light_direction" and not any(vector):
            raise RadfieldError(f"{where}: 'light_direction' must not be [0, 0, 0]")
        intensity = frame.get("light_intensity", 1.0)
        if not (_number(intensity) and intensity > 0):
            raise RadfieldError(f"{where}: 'light_intensity' must be a positive number, not {intensity!r:.40}")
        vector = tuple(float(x) for x in vector)
        if key == "light_position":
            return Light(position=vector, intensity=float(intensity))
        return Light(direction=vector, intensity=float(intensity))

    def row(self, light) -> dict[str, Any]:
        return self.to_json(light)   # {"position" | "direction", "intensity", "views", "psnr", ...}

    def from_row(self, row: dict[str, Any]):
        return self.from_json(row)

    def to_frame(self, light) -> dict[str, Any]:
        key, vector = ("light_position", light.position) if light.position is not None else ("light_direction", light.direction)
        return {key: list(vector), "light_intensity": light.intensity}

    def from_json(self, value: Any, where: str = ""):
        from radfield.core.geometry.cameras import Light

        return Light(value.get("position"), value.get("direction"), value["intensity"])

    def to_json(self, light) -> dict[str, Any]:
        key, vector = ("position", light.position) if light.position is not None else ("direction", light.direction)
        return {key: list(vector), "intensity": light.intensity}

    def normalized(self, light, normalization):
        """A point light moves with the cameras and its intensity grows by scale², so that the
        irradiance intensity / r² at every point of the scene is what it was (r grows by `scale`);
        a directional light is unchanged (a similarity keeps directions)."""
        import torch

        from radfield.core.geometry.cameras import Light

        if light.position is None:
            return light
        position = normalization.apply(torch.tensor(light.position, dtype=torch.float64))
        return Light(position=tuple(position.tolist()), intensity=light.intensity * normalization.scale**2)

    def check_views(self, placed, bounds) -> None:
        """No point light inside the object's bounds (module docstring)."""
        point_lit = [(where, light) for where, light in placed if light.position is not None]
        box = bounds() if point_lit else None
        if box is None:
            return
        for where, light in point_lit:
            if box.contains(light.position):
                raise RadfieldError(f"{where}: light_position [{', '.join(f'{x:.4g}' for x in light.position)}] is "
                                    f"inside the object's bounds ({box.describe()}): a point light must be outside "
                                    "the object")

    # --- asking --------------------------------------------------------------------------------------

    def options(self, verb: str) -> dict[str, Any]:
        import typer

        help = _HELP[verb]
        options = {
            "light": Annotated[Optional[str], typer.Option("--light", metavar="X,Y,Z", help=help["light"])],
            "light_dir": Annotated[Optional[str], typer.Option("--light-dir", metavar="X,Y,Z", help=help["light_dir"])],
            "light_intensity": Annotated[Optional[float], typer.Option("--light-intensity", help=help["light_intensity"])],
        }
        if verb == "render":
            options["light_orbit"] = Annotated[int, typer.Option("--light-orbit", metavar="N", help="A relightable model: N lights circling the object at the dataset lights' mean distance and elevation; one image per view and light (<view>_l<k>.png), or along an --orbit/--camera-path of N frames one light a frame.")]
        return options

    def asked(self, given: dict[str, Any]) -> Asked | None:
        light = light_from_options(given.get("light"), given.get("light_dir"), given.get("light_intensity"))
        orbit, intensity = given.get("light_orbit") or 0, given.get("light_intensity")
        if light is not None and orbit:
            raise RadfieldError(f"{light_option(light)} and --light-orbit exclude each other")
        if orbit < 0:
            raise RadfieldError(f"--light-orbit must be at least 0, got {orbit}")
        if intensity is not None and light is None and not orbit:
            what = "--light, --light-dir or --light-orbit" if "light_orbit" in given else "--light or --light-dir"
            raise RadfieldError(f"--light-intensity is the intensity of {what}: give one")
        if light is not None:
            return Asked(light_option(light), value=light, settings={"intensity": intensity})
        if orbit:
            return Asked("--light-orbit", values=(), settings={"count": orbit, "intensity": intensity})
        return None

    def resolved(self, asked: Asked, cameras, bounds) -> Asked:
        """One light: as bright as the dataset's (without --light-intensity) and outside the object;
        an orbit: `settings["count"]` lights about the centre of the object's bounds (else the
        cameras' focus) and the cameras' mean up (`orbit_lights`)."""
        recorded = [camera.conditions.get(self.name) for camera in cameras]
        if not asked.several:
            light = asked.value if asked.settings.get("intensity") is not None else as_bright_as(asked.value, recorded)
            check_outside(light, bounds(), asked.option)
            return replace(asked, value=light)
        if not cameras:
            raise RadfieldError("--light-orbit circles the dataset's lights: give --dataset for a model file")
        from radfield.core.geometry.camera_path import orbit_from_cameras

        params, box = orbit_from_cameras(cameras), bounds()
        centre = params["target"] if box is None else (box.center if box.center is not None else (box.low + box.high) / 2)
        return replace(asked, values=tuple(orbit_lights(recorded, centre, params["up"], asked.settings["count"],
                                                        asked.settings.get("intensity"))))

    def parse(self, text: str):
        from radfield.core.geometry.cameras import Light

        vector = parse_vector(text, "--at light")
        return Light(position=vector)

    # --- reporting -----------------------------------------------------------------------------------

    def label(self, light) -> str:
        where = ("at " if light.position is not None else "along ") + ", ".join(
            f"{x:.3g}" for x in (light.position if light.position is not None else light.direction))
        return f"{where} ({light.intensity:.4g})"

    def figures(self, light) -> dict[str, str]:
        vector = light.position if light.position is not None else light.direction
        return {"light" if light.position is not None else "light direction": ",".join(f"{x:g}" for x in vector),
                "light intensity": f"{light.intensity:g}"}


LIGHT = register(LightCondition())


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
