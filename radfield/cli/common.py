"""Helpers that the command modules of the CLI share: option parsing, device and model resolution,
the progress bar. Raise RadfieldError for user mistakes; main() prints them. Nothing here imports
torch at module level: `radfield --help` must not pay for it."""

from __future__ import annotations

import functools
import inspect
import math
from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield import conditions
from radfield.errors import RadfieldError
from radfield.util.numbers import three_numbers
from radfield.util.progress import progress_bar
from radfield.util.ranges import Range

__all__ = ["Background", "Dataset", "Device", "Downscale", "Force", "KINDS", "Quiet", "check_options", "check_output",
           "data_options", "kind_names", "parse_background", "progress_bar", "resolve_device", "resolve_model"]

# options shared by eval and bake
Dataset = Annotated[Optional[Path], typer.Option("--dataset", "-d", help="Dataset with the ground truth and the cameras (default: the run's input; its SfM output for photos).")]
Downscale = Annotated[Optional[int], typer.Option(help="Image downscale factor (default: the run's, else automatic: 1, or what data.max_size needs).")]
Background = Annotated[Optional[str], typer.Option(help="Background R,G,B (default: the run's, else 1,1,1).")]
Device = Annotated[str, typer.Option(help="cpu or cuda.")]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")]
# every command that writes an output folder or file (check_output)
Force = Annotated[bool, typer.Option("--force", help="Write even if OUTPUT exists and is not empty: a file is replaced, a folder's entries of the same names are replaced (others are kept). Never into a run directory.")]


def data_options(downscale: int | None, background: str | None) -> dict:
    options = {"data.downscale": downscale,
               "data.background": list(parse_background(background)) if background is not None else None}
    return {k: v for k, v in options.items() if v is not None}


KINDS = "KIND"   # the metavar of an option that takes a primitive kind: its help lists them (cli/main.py)


def kind_names() -> list[str]:
    """The registered primitive kinds, read from the registry's entry points (pyproject.toml,
    group radfield.kinds) without importing them (which needs torch): the base kinds, then their
    variants."""
    from importlib.metadata import entry_points

    return sorted({point.name for point in entry_points(group="radfield.kinds")}, key=lambda name: (name.count("-"), name))


def check_options(checks: dict[str, tuple[float | None, Range]]) -> None:
    """Each given option's number in its range ({"--fps": (fps, POSITIVE)}; None: not given), checked
    first, before anything is read or written: one line naming the option otherwise."""
    for option, (value, allowed) in checks.items():
        if value is not None and not allowed.holds(value):
            raise RadfieldError(f"{option} must be {allowed.describe()}, got {value:g}")


AT = Annotated[Optional[list[str]], typer.Option("--at", metavar="NAME=VALUE", help="A conditioned model: this value of a view condition for every view, e.g. time=0.5 (any registered condition; repeat for several conditions).")]
def condition_options(verb: str):
    """Decorator: add every registered view condition's options of `verb` (render, export, view;
    Condition.options, e.g. --time and --light) and `--at NAME=VALUE` to a command, and hand the
    command what they asked as `asked` (condition name -> conditions.Asked; each value checked,
    one line otherwise). The command declares `asked` where the options go and none of them."""

    def decorate(command):
        signature = inspect.signature(command, eval_str=True)
        owners: dict[str, conditions.Condition] = {}
        added = []
        for condition in conditions.registered():
            for name, annotation in condition.options(verb).items():
                owners[name] = condition
                default = 0 if annotation.__origin__ is int else None
                added.append(inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=annotation))
        added.append(inspect.Parameter("at", inspect.Parameter.KEYWORD_ONLY, default=None, annotation=AT))
        own = [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for p in signature.parameters.values()]
        cut = [p.name for p in own].index("asked")

        @functools.wraps(command)
        def with_conditions(**values):
            given = {name: values.pop(name) for name in owners}
            asked = {}
            for condition in conditions.registered():
                request = condition.asked({k: v for k, v in given.items() if owners[k] is condition})
                if request is not None:
                    asked[condition.name] = request
            for text in values.pop("at") or ():
                name, _, value = text.partition("=")
                if not value:
                    raise RadfieldError(f"--at takes NAME=VALUE, e.g. time=0.5, got {text!r}")
                condition = conditions.get(name.strip())
                if condition.name in asked:
                    raise RadfieldError(f"--at {text}: a {condition.name} is given twice ({asked[condition.name].option})")
                asked[condition.name] = conditions.Asked(f"--at {condition.name}", value=condition.parse(value.strip()))
            return command(**values, asked=asked)

        with_conditions.__signature__ = signature.replace(parameters=own[:cut] + added + own[cut + 1:])
        return with_conditions

    return decorate


def parse_background(text: str) -> tuple[float, float, float]:
    """'R,G,B' with components in [0, 1] (e.g. 1,1,1 for white)."""
    values = three_numbers(text)
    if values is None or not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in values):
        raise RadfieldError(f"--background must be three numbers in [0, 1] like 1,1,1, got {text!r}")
    return values


def resolve_device(name: str):
    import torch

    if name not in ("cpu", "cuda") and not name.startswith("cuda:"):
        raise RadfieldError(f"--device must be cpu or cuda[:N], got {name!r}")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise RadfieldError(f"--device {name}: this torch build sees no CUDA device (use --device cpu)")
    if name.startswith("cuda"):
        _warn_without_gpu_kernels(name)
    return torch.device(name)


def _warn_without_gpu_kernels(name: str) -> None:
    """One line on stderr when CUDA work cannot have the Triton kernels (not installed, too old) and
    falls back to the readable torch kernels, which are correct but many times slower; nothing when
    the user forced those (RADFIELD_KERNELS=torch)."""
    import sys

    from radfield.core import backends

    reason = backends.why_not(backends.TRITON)
    if reason is not None and not backends.forced_torch():
        oldest = ".".join(map(str, backends.gpu.MIN_TRITON))
        print(f"radfield: warning: --device {name}: {reason}, so CUDA runs the readable torch kernels, many "
              f"times slower (CUDA builds of torch 2.8 and later bring Triton {oldest} or newer)",
              file=sys.stderr, flush=True)


def resolve_model(path: Path) -> Path:
    """A model file, or a run directory whose final model is used."""
    from radfield.run import model_file

    return model_file(path)


def check_output(path: Path, force: bool, *, folder: bool) -> Path:
    """The one output policy of every command that writes (docs/usage.md, 'Outputs'), checked
    before any work. `path` may be missing or an empty folder; an existing file or non-empty
    folder is refused unless `force` (a file is then replaced, a folder's entries of the same
    names are); a run directory, or anything inside one, is refused even with `force`: a run
    is written by `reconstruct` and `edit` only, and a report or frames dropped into it would
    mix with (or, with --force, replace) its stage folders. `folder`: whether the command writes
    a folder (else a file)."""
    from radfield.run import is_run_dir

    path = Path(path)
    absolute = path.absolute()
    for parent in (absolute, *absolute.parents):
        if is_run_dir(parent):
            where = "is a radfield run directory" if parent == absolute else f"is inside the radfield run directory {parent}"
            raise RadfieldError(f"{path}: {where}; outputs are written beside a run, never into it (choose another --output)")
    if not path.exists() and not path.is_symlink():
        return path
    if folder:
        if not path.is_dir():
            raise RadfieldError(f"{path}: exists and is not a folder")
        if any(path.iterdir()) and not force:
            raise RadfieldError(f"{path}: already exists and is not empty (use --force to write into it)")
    else:
        if path.is_dir():
            raise RadfieldError(f"{path}: is a folder; give the file to write")
        if not force:
            raise RadfieldError(f"{path}: already exists (use --force to overwrite it)")
    return path
