"""Ranges of numbers: what a config key (pipeline/schema.py: `setting(range)`) or a command's option
(cli/common.py: check_options) accepts, and how an error line words it."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Range:
    """The values a numeric key takes (a list key: each of its items): from `low` to `high`
    (either may be open, or absent), or the one extra value `also` (e.g. -1: all cores); `note`
    says what a special value means, e.g. "0 = off". Floats must also be finite."""

    low: float | None = None
    high: float | None = None
    open_low: bool = False
    open_high: bool = False
    also: int | None = None
    note: str = ""

    def holds(self, value: float) -> bool:
        if value == self.also:
            return True
        if not math.isfinite(value):
            return False
        if self.low is not None and (value <= self.low if self.open_low else value < self.low):
            return False
        return self.high is None or (value < self.high if self.open_high else value <= self.high)

    def describe(self) -> str:
        if self.low is not None and self.high is not None:
            text = f"in {'(' if self.open_low else '['}{self.low:g}, {self.high:g}{')' if self.open_high else ']'}"
        elif self.low is not None:
            text = ("positive" if self.low == 0 else f"greater than {self.low:g}") if self.open_low else f"at least {self.low:g}"
        else:
            text = "a finite number"
        if self.also is not None:
            text = f"{self.also} or {text}"
        return f"{text} ({self.note})" if self.note else text


POSITIVE = Range(0, open_low=True)
AT_LEAST_0, AT_LEAST_1 = Range(0), Range(1)
FRACTION = Range(0, 1)
ELEVATION = Range(-90, 90, open_low=True, open_high=True, note="degrees")
