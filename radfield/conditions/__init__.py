"""The conditions a view may carry besides its camera (conditions/base.py: Condition), by name, in
registration order: time (conditions/time.py, Splat the Net appendix C.1) and light
(conditions/light.py, appendix C.2). The views' conditions choose the kind a run trains
(stages/init.primitive_kind); data.<condition> = ignore drops them (the time- or light-blind
baselines). A new one: a module that registers its Condition here, and a kind that reads it.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from radfield.conditions.base import Asked, Condition
from radfield.conditions.registry import get, names, register, registered, unregister
from radfield.errors import RadfieldError

def view_conditions(splits: dict[str, list[dict[str, Any]]]) -> tuple[str, ...]:
    """The conditions (registration order) that the views of scene.json's splits carry."""
    return tuple(c for c in names() if any(c in view for views in splits.values() for view in views))


def ignored(data_config: dict[str, Any]) -> set[str]:
    """The conditions whose data.<condition> is ignore (a condition without that key is never)."""
    return {c for c in names() if data_config.get(c) == "ignore"}


def without_ignored(scene: dict[str, Any], data_config: dict[str, Any]) -> dict[str, Any]:
    """The scene.json content without the conditions whose data.<condition> is ignore (the
    light-blind or time-blind baselines: a static kind trains on the views)."""
    dropped = ignored(data_config)
    if not dropped:
        return scene
    splits = {name: [{k: v for k, v in view.items() if k not in dropped} for view in views]
              for name, views in scene["splits"].items()}
    return {**scene, "splits": splits}


def distinct(splits: dict[str, list[dict[str, Any]]], name: str) -> list[Any]:
    """The distinct values (scene.json's form) of condition `name` over every view of scene.json's
    splits, sorted by the condition's key ([] when no view carries it)."""
    condition = get(name)
    values = {}
    for views in splits.values():
        for view in views:
            if name in view:
                values.setdefault(condition.key(condition.from_json(view[name])), view[name])
    return [values[k] for k in sorted(values)]


def view_values(view: dict[str, Any]) -> dict[str, Any]:
    """A scene.json VIEW's conditions as Camera.conditions holds them."""
    return {c.name: c.from_json(view[c.name]) for c in registered() if c.name in view}


def view_json(conditions: dict[str, Any]) -> dict[str, Any]:
    """Camera.conditions as a scene.json VIEW's entries (registration order)."""
    return {c.name: c.to_json(conditions[c.name]) for c in registered() if c.name in conditions}


def described(conditions: Iterable[str]) -> str:
    """'time-conditioned and relightable': the kind the conditions make a run train, in words."""
    return " and ".join(get(name).kind_words for name in conditions)


# --- a model and the conditions its kind reads (core/kinds: PrimitiveKind.conditions) ---------------

def taken(model) -> tuple[Condition, ...]:
    """The conditions the model's kind draws a view under."""
    from radfield.core import kinds

    return tuple(get(name) for name in kinds.of(model).conditions)


def check_takes(model, source, name: str, option: str) -> None:
    """An option of condition `name` given for a model whose kind does not read it: one error line
    (not ignored: its images would not change with the value)."""
    if get(name) not in taken(model):
        condition = get(name)
        raise RadfieldError(f"{source}: {option} is for a {condition.model_words} model; this one ({model.kind}) "
                            f"{condition.without} (leave out {option})")


def check_given(model, source, cameras, what: str) -> None:
    """A conditioned model draws every camera under its own value of each condition: one error
    line, before any output is written, when some camera has none (an orbit, a camera path, a
    dataset whose views carry none)."""
    for condition in taken(model):
        if any(condition.name not in camera.conditions for camera in cameras):
            raise RadfieldError(f"{source}: this model is {condition.model_words} ({model.kind}): give "
                                f"{condition.value_words} for {what} ({condition.how})")


def fixed(model, values: dict[str, Any]):
    """The static model of one value of each condition its kind reads (`values`: name -> value;
    the kind's at_conditions: at_time, eq. 10-13; at_light, eq. 14)."""
    from radfield.core import kinds

    return kinds.of(model).at_conditions(model, values)


# each registers itself; the order is the registry's (time before light)
from radfield.conditions import time  # noqa: E402,F401,I001
from radfield.conditions import light  # noqa: E402,F401,I001

__all__ = ["Asked", "Condition", "check_given", "check_takes", "described", "distinct", "fixed", "get", "ignored",
           "names", "register", "registered", "taken", "unregister", "view_conditions", "view_json", "view_values",
           "without_ignored"]
