"""Numbers a user types into an option."""

from __future__ import annotations


def three_numbers(text: str) -> tuple[float, float, float] | None:
    """'X,Y,Z' as three floats, or None when it is not three comma-separated numbers (each option
    says in its own error what it takes and checks its own range)."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        return None
    return values if len(values) == 3 else None
