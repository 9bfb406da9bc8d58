"""The animation spec of `radfield animate RUN --spec FILE -o OUT`: what the command's options say,
as a file (so an animation is reproducible from one file next to its cage frames).

    animate: {cages: PATTERN, camera: 0, split: test, orbit: false, elevation: 20, fps: 30,
              downscale: 1, background: [1, 1, 1], gradient: smooth, split_threshold: 0.5}
    simulate: {...}        # instead of animate.cages: the built-in soft-body simulation (simulate.py)

Exactly one pose source: `animate.cages` (a folder of cage frames or a glob pattern, relative to
the spec's folder) or `simulate:`. Every other key is optional; a key given in the spec takes
the place of the command-line option of the same name (split_threshold: --split-threshold).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from radfield.errors import RadfieldError
from radfield.edit.affine import CAGE_GRADIENTS as GRADIENTS   # an animation has cage poses only: no "map"
from radfield.edit.select import number, vector
from radfield.edit.simulate import parse_simulation
from radfield.edit.spec import check_keys, read_yaml

RENDER_KEYS = ("camera", "split", "orbit", "elevation", "fps", "downscale", "background", "gradient", "split_threshold")


def read_animation(path: str | Path) -> dict[str, Any]:
    """{"cages": str or None, "simulate": checked parameters or None, and the RENDER_KEYS given}."""
    path = Path(path)
    data = read_yaml(path, "the animation spec")
    where = str(path)
    if not isinstance(data, Mapping) or not data:
        raise RadfieldError(f"{where}: an animation spec is a mapping with 'animate:' and/or 'simulate:'")
    check_keys(data, {"animate", "simulate"}, where)
    anim = data.get("animate") or {}
    if not isinstance(anim, Mapping):
        raise RadfieldError(f"{where}: animate: expected a mapping, got {anim!r}")
    w = f"{where}: animate"
    check_keys(anim, {"cages", *RENDER_KEYS}, w)
    has_cages, has_sim = "cages" in anim, "simulate" in data
    if has_cages == has_sim:
        raise RadfieldError(f"{where}: give exactly one pose source, animate.cages or simulate:")
    out: dict[str, Any] = {"cages": None, "simulate": None}
    if has_cages:
        cages = anim["cages"]
        if not isinstance(cages, str) or not cages:
            raise RadfieldError(f"{w}.cages: expected a folder or a glob pattern, got {cages!r}")
        out["cages"] = cages if Path(cages).expanduser().is_absolute() else str(path.parent / cages)
    else:
        out["simulate"] = parse_simulation(data["simulate"] or {}, f"{where}: simulate")
    if "camera" in anim:   # a frame name, or an index in the split
        value = anim["camera"]
        if isinstance(value, bool) or not (isinstance(value, int) and value >= 0 or isinstance(value, str) and value):
            raise RadfieldError(f"{w}.camera: expected a frame name or an index >= 0, got {value!r}")
        out["camera"] = str(value)
    if "downscale" in anim:
        value = anim["downscale"]
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise RadfieldError(f"{w}.downscale: expected an integer >= 1, got {value!r}")
        out["downscale"] = value
    for key in ("elevation", "fps", "split_threshold"):
        if key in anim:
            out[key] = number(anim, key, w, positive=key == "fps")
            if key == "split_threshold" and out[key] < 0:
                raise RadfieldError(f"{w}.split_threshold: must be >= 0, got {out[key]}")
    if "orbit" in anim:
        if not isinstance(anim["orbit"], bool):
            raise RadfieldError(f"{w}.orbit: expected true or false, got {anim['orbit']!r}")
        out["orbit"] = anim["orbit"]
    if "split" in anim:
        if anim["split"] not in ("train", "val", "test"):
            raise RadfieldError(f"{w}.split: expected train, val or test, got {anim['split']!r}")
        out["split"] = anim["split"]
    if "gradient" in anim:
        if anim["gradient"] not in GRADIENTS:
            raise RadfieldError(f"{w}.gradient: expected one of {', '.join(GRADIENTS)}, got {anim['gradient']!r}")
        out["gradient"] = anim["gradient"]
    if "background" in anim:
        rgb = vector(anim, "background", w)
        if not ((rgb >= 0) & (rgb <= 1)).all():
            raise RadfieldError(f"{w}.background: expected numbers in [0, 1], got {rgb.tolist()}")
        out["background"] = ",".join(str(float(c)) for c in rgb)
    return out
