"""The `radfield` command line (Typer): the app, its error handling, and the registry of the
commands (`COMMANDS`, in help order), one module per command in radfield/cli/ (every `bench-*`
benchmark in cli/bench.py).

A command module parses its options, calls the library and prints; it imports torch and the
other heavy libraries inside the command, so that `radfield --help` and `radfield COMMAND --help`
start in a fraction of a second (tests/test_imports.py, `radfield bench-startup`). A RadfieldError
becomes one line on stderr and exit code 1; anything else is a bug and keeps its traceback."""

from __future__ import annotations

import sys
import types
from collections.abc import Callable
from typing import Annotated

import typer
from typer.core import TyperCommand, TyperGroup

import radfield
from radfield.cli import (animate, bake, bench, demo_scene, edit, eval as eval_, export, import_model, info, reconstruct, render,
                          view)
from radfield.cli.common import KINDS, kind_names
from radfield.errors import RadfieldError
from radfield.util.registry import Registry


def _click():
    """The Click that Typer runs on: its vendored copy (Typer >= 0.20, typer._click) or Click."""
    try:
        import typer._click as click
    except ImportError:
        import click
    return click


_NO_BREAK = "\u2011"   # a non-breaking hyphen stands for "-" while help text is wrapped


class _Formatter(_click().HelpFormatter):
    """Click's plain help layout, wrapped to the terminal's width, which never breaks a line inside
    a hyphenated word: an option name (--light-orbit) stays whole."""

    def write_text(self, text: str) -> None:
        super().write_text(text.replace("-", _NO_BREAK))

    def write_dl(self, rows, *args, **kwargs) -> None:
        super().write_dl([(first, second.replace("-", _NO_BREAK)) for first, second in rows], *args, **kwargs)

    def getvalue(self) -> str:
        return super().getvalue().replace(_NO_BREAK, "-")


class _Context(_click().Context):
    formatter_class = _Formatter


class _Command(TyperCommand):
    """A command whose help lists the registered primitive kinds for an option whose metavar is
    KINDS (read when the help is shown: the registry's entry points, without importing the kinds)."""

    context_class = _Context

    def format_help(self, ctx, formatter) -> None:
        for param in self.params:
            if param.metavar == KINDS and "Registered kinds:" not in (param.help or ""):
                param.help = f"{param.help} Registered kinds: {', '.join(kind_names())}."
        super().format_help(ctx, formatter)


class _Group(TyperGroup):
    """The root: its commands in two lists, what a user runs and the benchmarks, each command's
    summary whole (Click cuts it with "..." to one line)."""

    context_class = _Context

    def format_commands(self, ctx, formatter) -> None:
        rows = {"Commands": [], "Benchmarks": []}
        for name in self.list_commands(ctx):
            command = self.get_command(ctx, name)
            if command is not None and not command.hidden:
                rows["Benchmarks" if name.startswith("bench-") else "Commands"].append(
                    (name, command.get_short_help_str(limit=10_000)))
        for title, section in rows.items():
            if section:
                with formatter.section(title):
                    formatter.write_dl(section)


app = typer.Typer(
    name="radfield",
    help="Reconstruct, edit, render and evaluate radiance fields made of splattable neural primitives.",
    cls=_Group,
    # Click's plain layout: paragraphs rewrapped to the terminal, nothing cut with "…", no Rich
    # markup (which turned `--times A:B:N` into an emoji), flags without a type
    rich_markup_mode=None,
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(value: bool):
    if value:
        typer.echo(f"radfield {radfield.__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                                help="Print the version and exit.")] = False):
    """radfield: editable radiance fields from multi-view images."""


# the verbs, registered in the order `radfield --help` lists them, the README's: the commands, then
# the benchmarks (a new verb: its module in radfield/cli/ and one line here)
COMMANDS: Registry[Callable] = Registry("command")
for _name, _function in (("reconstruct", reconstruct.reconstruct), ("import", import_model.import_model), ("info", info.info),
                         ("render", render.render), ("eval", eval_.eval_command), ("bake", bake.bake), ("edit", edit.edit),
                         ("animate", animate.animate), ("export", export.export), ("view", view.view),
                         ("demo-scene", demo_scene.demo_scene), ("bench-quality", bench.bench_quality),
                         ("bench-render", bench.bench_render), ("bench-train", bench.bench_train), ("bench-web", bench.bench_web),
                         ("bench-dist", bench.bench_dist), ("bench-startup", bench.bench_startup)):
    COMMANDS.register(_name, _function)
for _name, _function in COMMANDS.items():
    app.command(_name, cls=_Command)(_function)
del _name, _function


def command_names(typer_app: typer.Typer) -> list[str]:
    """The names of the app's commands, in registration order."""
    return [command.name for command in typer_app.registered_commands]


def main() -> None:
    """The console entry point: every user mistake, on every command, is one line
    `radfield: error: …` on stderr and exit code 1 (a RadfieldError from the work, or a usage
    error Click finds while parsing: a wrong option type, a missing or unknown option)."""
    click = _click_exceptions()
    try:
        code = app(standalone_mode=False, prog_name="radfield")
    except click.NoArgsIsHelpError as e:  # bare `radfield` or a group without a command (Click ≥ 8.2)
        typer.echo(e.ctx.get_help())
        code = 0
    except click.UsageError as e:
        command = e.ctx.command_path if e.ctx is not None else "radfield"
        message = " ".join(e.format_message().split())
        typer.echo(f"radfield: error: {message} (see '{command} --help')", err=True)
        sys.exit(1)
    except click.ClickException as e:  # e.g. a file Click could not open
        typer.echo(f"radfield: error: {' '.join(e.format_message().split())}", err=True)
        sys.exit(1)
    except RadfieldError as e:
        typer.echo(f"radfield: error: {e}", err=True)
        sys.exit(1)
    except (KeyboardInterrupt, typer.Abort):
        typer.echo("radfield: interrupted", err=True)
        sys.exit(130)
    if isinstance(code, int) and code:  # typer.Exit(code) returns its code without standalone mode
        sys.exit(code)


def _click_exceptions():
    """Click's exception classes: Typer ≥ 0.20 vendors Click as typer._click, older Typer uses Click.
    Click < 8.2 has no NoArgsIsHelpError (it prints the help and exits 0 itself): a class nothing
    raises stands in for it there."""
    exceptions = _click().exceptions
    if not hasattr(exceptions, "NoArgsIsHelpError"):
        never_raised = type("NoArgsIsHelpError", (Exception,), {})
        exceptions = types.SimpleNamespace(**vars(exceptions), NoArgsIsHelpError=never_raised)
    return exceptions


if __name__ == "__main__":
    main()
