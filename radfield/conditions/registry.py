"""The registry of view conditions (conditions/__init__.py), apart so that a condition's module
registers itself without importing the package that imports it."""

from __future__ import annotations

from radfield.conditions.base import Condition
from radfield.util.registry import Registry

_CONDITIONS: Registry[Condition] = Registry("view condition")


def register(condition: Condition) -> Condition:
    """Add `condition` (ValueError when its name is taken)."""
    return _CONDITIONS.register(condition.name, condition)


def unregister(name: str) -> None:
    """Forget condition `name` (tests clean up with it)."""
    _CONDITIONS.unregister(name)


def get(name: str) -> Condition:
    return _CONDITIONS.get(name)


def registered() -> tuple[Condition, ...]:
    return _CONDITIONS.values()


def names() -> tuple[str, ...]:
    return _CONDITIONS.names()
