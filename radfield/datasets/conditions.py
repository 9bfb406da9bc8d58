"""What a dataset's views may carry besides their camera, in scene.json (datasets/scene.py): a
condition of the view, the moment it shows (time) or the light it is lit by (light). The views'
conditions choose the kind a run trains (stages/init.primitive_kind); data.<condition> = ignore
drops them (the time- or light-blind baselines)."""

from __future__ import annotations

import json
from typing import Any


# What a view may carry besides its camera (a scene.json VIEW key each), and so condition the kind
# the run trains (stages/init.primitive_kind), with that kind in words (for messages). A new one
# also gets its config key data.<condition>: auto | ignore (pipeline.yaml, pipeline/config.CHOICES)
CONDITIONS = {"time": "time-conditioned", "light": "relightable"}


def view_conditions(splits: dict[str, list[dict[str, Any]]]) -> tuple[str, ...]:
    """The conditions (CONDITIONS order) that the views of scene.json's splits carry."""
    return tuple(c for c in CONDITIONS if any(c in view for views in splits.values() for view in views))


def without_ignored(scene: dict[str, Any], data_config: dict[str, Any]) -> dict[str, Any]:
    """The scene.json content without the conditions whose data.<condition> is ignore (the
    light-blind or time-blind baselines of issues 29 and 30: a static kind trains on the views)."""
    ignored = {c for c in CONDITIONS if data_config.get(c) == "ignore"}
    if not ignored:
        return scene
    splits = {name: [{k: v for k, v in view.items() if k not in ignored} for view in views]
              for name, views in scene["splits"].items()}
    return {**scene, "splits": splits}


def scene_times(scene: dict[str, Any]) -> list[float]:
    """The distinct times of a scene.json's views, ascending ([] for a static scene)."""
    return sorted({view["time"] for views in scene["splits"].values() for view in views if "time" in view})


def scene_lights(scene: dict[str, Any]) -> list[str]:
    """The distinct lights of a scene.json's views, as JSON text ([] under fixed lighting)."""
    return sorted({json.dumps(view["light"], sort_keys=True) for views in scene["splits"].values()
                   for view in views if "light" in view})
