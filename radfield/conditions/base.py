"""What a view may carry besides its camera, as one object: a `Condition` (the moment it shows, the
light it is lit by, ...). Everything radfield does with one goes through it, so a new condition is
one module that registers a Condition plus the kind that reads it (core/kinds: `conditions`):

    reading     read_frame (a transforms.json frame), from_json / to_json (a scene.json VIEW),
                normalized (into the training frame), check_views (the dataset's views together)
    drawing     Camera.conditions[name] holds the value; a kind with `name` in its `conditions`
                reads it (at_view) and fixes it (at_conditions: the static model of one value)
    asking      options (the CLI flags of render, export and view), asked (their values ->
                an `Asked`), resolved (the values an `Asked` means for a dataset's views), parse
                (the text of `--at NAME=VALUE`)
    reporting   words for messages, a label per value, figures of the data stage and eval

Light to import: no torch (the CLI builds its options from here before anything heavy loads).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from radfield.errors import RadfieldError


@dataclass(frozen=True)
class Asked:
    """What the options asked of one condition: `value` for every view, or each of `values` (one
    image a view and value, or along a camera path one value a frame). `option` is the flag that
    asked (for messages); `settings` holds what resolving needs besides (e.g. a light's intensity)."""

    option: str
    value: Any = None
    values: tuple | None = None
    settings: dict[str, Any] = field(default_factory=dict)

    @property
    def several(self) -> bool:
        return self.values is not None


class Condition:
    """One condition of a view (module docstring). Subclasses set the words and override what
    differs from a plain JSON value that needs no conversion."""

    name: str = ""            # the scene.json VIEW key, Camera.conditions key, `--at NAME=`, data.<name>
    plural: str = ""          # "times": the data stage's figure of distinct values, and its log line
    unit: str = ""            # "moments": those values in `radfield info`
    model_words: str = ""     # "dynamic": a model whose kind reads it ("a dynamic model")
    kind_words: str = ""      # "time-conditioned": the kind the views make a run train
    without: str = "is not"   # what a model without it is, after "this one (gaussian)"
    value_words: str = ""     # "a time": one value, in "give a time for the orbit"
    how: str = ""             # the options that give one, in messages: "--time T, or --times A:B:N"
    tag: str = ""             # frame names of several values: <view>_<tag><k>
    drawn: tuple[str, str] = ("at", "value")   # "4 views at 24 moments": how render says what it drew
    pairing: str = "the path's frames and the values pair one to one"   # several values along a path
    once: str = "one value"   # what a file of the static model holds: "ply-3dgs holds one moment"
    how_once: str = ""        # the options that give that one value, in messages

    @property
    def frame_words(self) -> tuple[str, str]:
        """How a message says a transforms.json frame has one, or has none."""
        return f"a '{self.name}'", f"no '{self.name}'"

    @property
    def frame_hint(self) -> str:
        """What a dataset whose frames disagree should do."""
        return f"give every frame a '{self.name}' or none"

    # --- reading ------------------------------------------------------------------------------------

    def in_frame(self, frame: dict[str, Any]) -> bool:
        """Whether a transforms.json frame gives one (checked all or none across a dataset's frames
        before the value is). Default: the frame has the key `name`."""
        return self.name in frame

    def read_frame(self, frame: dict[str, Any], where: str) -> Any:
        """The value a transforms.json frame gives (None when it has none); a bad one raises,
        `where` naming the file and frame. Default: the frame's key `name`, as from_json takes it."""
        return None if self.name not in frame else self.from_json(frame[self.name], where)

    def to_frame(self, value: Any) -> dict[str, Any]:
        """The transforms.json frame keys that give `value` (what read_frame reads back)."""
        return {self.name: self.to_json(value)}

    def from_json(self, value: Any, where: str = "") -> Any:
        """The value of a scene.json VIEW's entry (checked)."""
        return value

    def to_json(self, value: Any) -> Any:
        """The scene.json VIEW's entry of `value`."""
        return value

    def normalized(self, value: Any, normalization) -> Any:
        """`value` in the training frame (datasets/scene.py: Normalization); most do not move."""
        return value

    def check_views(self, placed: Sequence[tuple[str, Any]], bounds: Callable[[], Any]) -> None:
        """The views of a dataset together, once every view has its camera: `placed` is (where, value)
        per view carrying one, `bounds()` the object's bounds (datasets/bounds.py) or None."""

    # --- asking --------------------------------------------------------------------------------------

    def options(self, verb: str) -> dict[str, Any]:
        """The CLI options of `verb` (render, export or view): parameter name -> typer `Annotated`
        type (cli/common.condition_options adds them to the command; each defaults to None, an int
        to 0). Render may take several values; export and view show one."""
        return {}

    def asked(self, given: dict[str, Any]) -> Asked | None:
        """What the option values `given` (parameter name -> value, None when not given) ask for, or
        None. Checks each value and their combination (one line each)."""
        return None

    def resolved(self, asked: Asked, cameras: Sequence[Any], bounds: Callable[[], Any]) -> Asked:
        """`asked` with concrete values for a dataset split whose views are `cameras` (each with its
        own conditions; [] without a dataset), `bounds()` the object's bounds or None. Default: as
        asked."""
        return asked

    def parse(self, text: str) -> Any:
        """The value of `--at NAME=TEXT`. Default: a JSON value, as scene.json holds it."""
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            raise RadfieldError(f"--at {self.name}=VALUE takes a JSON value, got {text!r}") from None
        return self.from_json(value, f"--at {self.name}")

    # --- reporting -----------------------------------------------------------------------------------

    def label(self, value: Any) -> str:
        """`value` in a table or a figure line."""
        return json.dumps(self.to_json(value), sort_keys=True)

    def figures(self, value: Any) -> dict[str, str]:
        """`value` among the figures of an export's summary line (`radfield export ... (time 0.5)`)."""
        return {self.name: self.label(value)}

    def row(self, value: Any) -> dict[str, Any]:
        """`value` as the leading entries of its row in metrics.json's per_<name> (evaluation/metrics.py)."""
        return {self.name: self.to_json(value)}

    def from_row(self, row: dict[str, Any]) -> Any:
        """The value of such a row."""
        return self.from_json(row[self.name])

    def key(self, value: Any) -> Any:
        """What groups the views of one value (sortable, hashable): their JSON text."""
        return json.dumps(self.to_json(value), sort_keys=True)

    def ordered(self) -> bool:
        """Whether per-value tables sort by `key` (moments do); else in the order values appear."""
        return False

    def __repr__(self) -> str:
        return f"<condition {self.name}>"

