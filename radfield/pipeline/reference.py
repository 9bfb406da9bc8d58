"""docs/configuration.md, the configuration reference: every key of the schema (pipeline/schema.py)
with its type, its default (pipeline.yaml), its range or choices, the flag that sets it and its
docstring. Regenerate it after changing either file (tests/test_config_reference.py compares):

    python -m radfield.pipeline.reference > docs/configuration.md
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

from radfield.pipeline import schema
from radfield.pipeline.config import describe, load_defaults, value_at
from radfield.pipeline.schema import Config, Key, Section

HEADER = """\
# Configuration reference

Every key a run can use, generated from `radfield/pipeline/schema.py` (types, ranges, meanings)
and `radfield/pipeline.yaml` (the defaults) by `python -m radfield.pipeline.reference >
docs/configuration.md`; do not edit it by hand. Set a key with `--set key=value` or in a
`--config FILE` (a partial copy of `pipeline.yaml`); a flag in the key's column sets it too. How
configuration works: [usage.md: Configuration](usage.md#configuration-pipelineyaml).
"""


def render() -> str:
    """The whole reference as Markdown."""
    defaults = load_defaults()
    parts = [HEADER]
    sections = [(name, schema.find(name)) for name in schema.names() if not isinstance(schema.find(name), Key)]
    for name, cls in [("", Config), *sections]:
        parts.append(_section(name, cls, defaults))
    return "\n".join(parts)


def _section(name: str, cls: type[Section], defaults: dict[str, Any]) -> str:
    title = f"`{name}`" if name else "Top level"
    lines = [f"## {title}", "", " ".join((cls.__doc__ or "").split()), "",
             "| key | type | default | allowed | what it is |", "| --- | --- | --- | --- | --- |"]
    docs = schema.docs(cls)
    for spec in dataclasses.fields(cls):
        key = schema.find(f"{name}.{spec.name}" if name else spec.name)
        if not isinstance(key, Key):
            continue
        flag = f" (`{key.flag}`)" if key.flag else ""
        cells = [f"`{key.name}`{flag}", describe(key).split(" ", 1)[1], f"`{_yaml(value_at(defaults, key.name))}`",
                 _allowed(key), docs[spec.name]]
        lines.append("| " + " | ".join(cell.replace("|", "\\|") for cell in cells) + " |")
    return "\n".join(lines) + "\n"


def _allowed(key: Key) -> str:
    if key.selection:
        return "any of the default's entries, each once, in any order"
    choices = key.choices() if callable(key.choices) else key.choices
    if choices:
        return "one of " + ", ".join(f"`{choice}`" for choice in choices)
    if key.range is not None:
        return ("each " if key.is_list else "") + key.range.describe()
    return ""


def _yaml(value: Any) -> str:
    """A value as pipeline.yaml writes it (strings bare)."""
    if isinstance(value, list):
        return "[" + ", ".join(_yaml(item) for item in value) + "]"
    return value if isinstance(value, str) else json.dumps(value)


def main() -> None:
    print(render(), end="")


if __name__ == "__main__":
    main()
