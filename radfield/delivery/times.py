"""The moments a dynamic model is drawn or exported at (Splat the Net appendix C.1; issue 29):
`--time T` and `--times A:B:N` of `radfield render`, `export` and `view`.

A time-conditioned kind (core/kinds/dynamic.py) shows one moment ξ ∈ [0, 1] per view: render()
reads Camera.time, and `kind.at_time(prims, ξ)` is the static model of that moment. Which kind is
dynamic is asked of the kind registry (`conditions`), never branched on by name. A time given for
a static model is refused (one line), not ignored: a static model shows one moment, so a --times
render would write N identical images and an export "at T" would silently be every moment.
Light to import (no torch): the CLI checks options with it before loading anything.
"""

from __future__ import annotations

import math
from dataclasses import replace

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


def is_dynamic(model) -> bool:
    """Whether the model's kind draws a view at the view's time (its `conditions` hold "time")."""
    from radfield.core import kinds

    return "time" in kinds.of(model).conditions


def check_takes_time(model, source, option: str = "--time") -> None:
    """A time option given for a static model: one error line (module docstring: why not a note)."""
    if not is_dynamic(model):
        raise RadfieldError(f"{source}: {option} is for a dynamic model; this one ({model.kind}) is static and shows "
                            f"one moment (leave out {option})")


def check_timed(model, source, cameras, what: str) -> None:
    """A dynamic model draws every camera at its own time: one error line, before any output is
    written, when some camera has none (an orbit, a camera path, a static dataset's views)."""
    if is_dynamic(model) and any(camera.time is None for camera in cameras):
        raise RadfieldError(f"{source}: this model is dynamic ({model.kind}): give a time for {what} "
                            "(--time T, or --times A:B:N)")


def at_time(cameras, time: float) -> list:
    """The cameras showing moment `time`."""
    return [replace(camera, time=time) for camera in cameras]


def model_at(model, time: float):
    """The static model of a dynamic one at moment `time` (its kind's `at_time`, eq. 10-13)."""
    from radfield.core import kinds

    return kinds.of(model).at_time(model, time)
