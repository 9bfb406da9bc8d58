"""Time: the moment ξ_t ∈ [0, 1] a view shows (Splat the Net appendix C.1; issue 29).

A dynamic dataset (D-NeRF, nerfstudio with time) gives each frame a `time`; every frame carries one
or none does, so a scene is wholly static or wholly dynamic. The time-conditioned kinds
(core/kinds/dynamic.py) read Camera.conditions["time"] and fix it (`at_time`, eq. 10-13).
`radfield render`, `export` and `view` take `--time T`; render also `--times A:B:N`, N moments
from A to B (one image a view and moment, or along an orbit or a camera path a time-lapse).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Optional

from radfield.conditions.base import Asked, Condition
from radfield.conditions.registry import register
from radfield.errors import RadfieldError


def check_time(value: float, option: str = "--time") -> float:
    """`value` if it is a moment ξ ∈ [0, 1] (a dynamic scene's times run from 0 to 1)."""
    if not (math.isfinite(value) and 0.0 <= value <= 1.0):
        raise RadfieldError(f"{option} must be a moment in [0, 1] (a dynamic scene runs from time 0 to 1), got {value:g}")
    return float(value)


def parse_times(text: str) -> list[float]:
    """`--times A:B:N`: N evenly spaced moments from A to B (both included; N = 1: A alone)."""
    parts = text.split(":")
    try:
        if len(parts) != 3:
            raise ValueError
        start, stop, count = float(parts[0]), float(parts[1]), int(parts[2])
    except ValueError:
        raise RadfieldError(f"--times takes START:STOP:COUNT, e.g. 0:1:24 (COUNT moments from START to STOP), got {text!r}") from None
    if count < 1:
        raise RadfieldError(f"--times {text}: COUNT must be at least 1, got {count}")
    check_time(start, f"--times {text}: START")
    check_time(stop, f"--times {text}: STOP")
    if count == 1:
        return [start]
    return [start + (stop - start) * k / (count - 1) for k in range(count)]


_TIME_HELP = {
    "render": "A dynamic model: draw every view at this moment in [0, 1] (default: each dataset view at its own time).",
    "export": "A dynamic model: ply-3dgs, splat and points of the moment T in [0, 1] (a static model of that moment; required for a dynamic model).",
    "view": "A dynamic model: the moment in [0, 1] shown first (the viewer's Time slider moves it).",
}


class Time(Condition):
    name, plural, unit, model_words, kind_words = "time", "times", "moments", "dynamic", "time-conditioned"
    without, value_words, how, tag = "is static and shows one moment", "a time", "--time T, or --times A:B:N", "t"

    frame_words, frame_hint = ("a 'time'", "no 'time'"), "give every frame a time or none"
    drawn, pairing = ("at", "moment"), "a time-lapse pairs them one to one"
    once, how_once = "one moment", "--time T, T in [0, 1]"

    def from_json(self, value: Any, where: str = "") -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise RadfieldError(f"{where}: 'time' must be a number in [0, 1], not {value!r:.40}")
        if not 0.0 <= value <= 1.0:
            raise RadfieldError(f"{where}: 'time' {value!r} is outside [0, 1]")
        return value

    def options(self, verb: str) -> dict[str, Any]:
        import typer

        options = {"time": Annotated[Optional[float], typer.Option("--time", help=_TIME_HELP[verb])]}
        if verb == "render":
            options["times"] = Annotated[Optional[str], typer.Option("--times", metavar="A:B:N", help="A dynamic model: N moments from A to B; one image per view and moment (<view>_t<k>.png), or along an --orbit/--camera-path of N frames a time-lapse, one moment a frame.")]
        return options

    def asked(self, given: dict[str, Any]) -> Asked | None:
        time, times = given.get("time"), given.get("times")
        if time is not None and times is not None:
            raise RadfieldError("--time and --times exclude each other")
        if time is not None:
            return Asked("--time", value=check_time(time))
        if times is not None:
            return Asked("--times", values=tuple(parse_times(times)))
        return None

    def parse(self, text: str) -> float:
        try:
            return check_time(float(text), "--at time")
        except ValueError:
            raise RadfieldError(f"--at time=T takes a moment in [0, 1], got {text!r}") from None

    def label(self, value: float) -> str:
        return f"{value:.4g}"

    def figures(self, value: float) -> dict[str, str]:
        return {"time": f"{value:g}"}

    def key(self, value: float) -> float:
        return value

    def ordered(self) -> bool:
        return True


TIME = register(Time())
