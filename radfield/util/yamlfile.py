"""The one YAML loader of every file radfield reads (the pipeline config, edit, animation and
simulation specs, a run's config.yaml), and the one wording of its syntax errors."""

from __future__ import annotations

import re
from typing import Any

import yaml


class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads `1e-5`, `1e3`, `1E6` and `.5e3` as floats (YAML 1.2), as users
    write them: YAML 1.1 (PyYAML's default) wants a dot and a signed exponent (`1.0e+6`), so `1e6`
    was the string '1e6'. The one loader of every YAML file radfield reads (the pipeline config,
    edit, animation and simulation specs: radfield.edit.spec.read_yaml)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+.0123456789"),
)


def parse_yaml(text: str) -> Any:
    """Parse YAML text with the project's loader (safe; YAML 1.2 floats)."""
    return yaml.load(text, Loader=_Loader)


def yaml_problem(error: yaml.YAMLError) -> str:
    """What is wrong in a YAML text and where, in one line: "expected ',' or ']', but got '<stream
    end>' (line 3, column 1)". Every YAML file radfield reads words its syntax errors so."""
    mark = getattr(error, "problem_mark", None)
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    return f"{problem} (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else problem
