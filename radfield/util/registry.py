"""A registry of named things: the shape every extension point shares, so that each module keeps
only what is its own (what it checks before registering, the order it lists them in).

    KINDS = Registry("primitive kind")
    KINDS.register(name, thing)   ValueError "primitive kind 'x' is registered already"
    KINDS.unregister(name)        forget it (nothing when it is not there)
    KINDS.get(name)               RadfieldError "unknown primitive kind 'x' (known: a, b)"
    KINDS.names(), KINDS.values(), KINDS.items()
                                  in registration order, or sorted by `order` (stable)

Every extension point keeps its things in one: the primitive kinds (core/kinds), the dataset
formats (datasets/formats), the kernel backends (core/backends, ordered by rank), the edit
operations (edit/spec.py), the stages (stages/registry.py), the commands (cli/main.py), the view
conditions (conditions) and the demo scenes (demo).

Standard library only: the registries are built at import time of modules that must stay light
(`radfield --help` imports the dataset formats; docs/design.md "Light start-up").
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Generic, TypeVar

from radfield.errors import RadfieldError

T = TypeVar("T")


class Registry(Generic[T]):
    """Things of one kind by name. `what` names the kind in messages; `order(thing)`, when given,
    is the key names() and values() sort by (equal keys keep their registration order)."""

    def __init__(self, what: str, order: Callable[[T], Any] | None = None):
        self.what = what
        self._order = order
        self._items: dict[str, T] = {}

    def register(self, name: str, thing: T) -> T:
        """Add `thing` as `name` and return it; ValueError when the name is taken (a second
        registration is a programming mistake, never a user's)."""
        if name in self._items:
            raise ValueError(f"{self.what} {name!r} is registered already")
        self._items[name] = thing
        return thing

    def unregister(self, name: str) -> None:
        """Forget `name` (nothing when it is not registered: tests and plugins clean up with it)."""
        self._items.pop(name, None)

    def get(self, name: str) -> T:
        """The thing called `name`; a one-line RadfieldError listing the known names when none is
        (e.g. a file written by a process that had a plugin registered)."""
        try:
            return self._items[name]
        except KeyError:
            raise RadfieldError(f"unknown {self.what} {name!r} (known: {', '.join(self.names())})") from None

    def __contains__(self, name: object) -> bool:
        return name in self._items

    def values(self) -> tuple[T, ...]:
        """Every registered thing, in registration order or by `order`."""
        things = tuple(self._items.values())
        return things if self._order is None else tuple(sorted(things, key=self._order))

    def names(self) -> tuple[str, ...]:
        """Every registered name, in the order of values()."""
        return tuple(name for name, _ in self.items())

    def items(self) -> tuple[tuple[str, T], ...]:
        """Every (name, thing), in the order of values()."""
        items = tuple(self._items.items())
        return items if self._order is None else tuple(sorted(items, key=lambda item: self._order(item[1])))
