"""The `radfield` command line (Typer): the app, its error handling, and the registration of the
commands, one module per command in radfield/cli/ (every `bench-*` benchmark in cli/bench.py).

A command module parses its options, calls the library and prints; it imports torch and the
other heavy libraries inside the command, so that `radfield --help` and `radfield COMMAND --help`
start in a fraction of a second (tests/test_imports.py, `radfield bench-startup`). A RadfieldError
becomes one line on stderr and exit code 1; anything else is a bug and keeps its traceback."""

from __future__ import annotations

import sys
import types
from typing import Annotated

import typer

import radfield
from radfield.cli import animate, bake, bench, demo_scene, edit, eval as eval_, export, info, reconstruct, render, view
from radfield.errors import RadfieldError

app = typer.Typer(
    name="radfield",
    help="Reconstruct, edit, render and evaluate radiance fields made of splattable neural primitives.",
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


# in the order `radfield --help` lists them
app.command("reconstruct")(reconstruct.reconstruct)
app.command("info")(info.info)
app.command("render")(render.render)
app.command("bench-render")(bench.bench_render)
app.command("bench-train")(bench.bench_train)
app.command("bench-dist")(bench.bench_dist)
app.command("demo-scene")(demo_scene.demo_scene)
app.command("edit")(edit.edit)
app.command("animate")(animate.animate)
app.command("eval")(eval_.eval_command)
app.command("bake")(bake.bake)
app.command("bench-quality")(bench.bench_quality)
app.command("bench-startup")(bench.bench_startup)
app.command("export")(export.export)
app.command("view")(view.view)


def command_names(typer_app: typer.Typer) -> list[str]:
    """The names of the app's commands, in registration order."""
    return [command.name for command in typer_app.registered_commands]


def main() -> None:
    """The console entry point: every user mistake, on every command, is one line
    `radfield: error: …` on stderr and exit code 1 (a RadfieldError from the work, or a usage
    error Click finds while parsing: a wrong option type, a missing or unknown option)."""
    click = _click_exceptions()
    try:
        code = app(standalone_mode=False)
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
    try:
        from typer._click import exceptions
    except ImportError:
        from click import exceptions
    if not hasattr(exceptions, "NoArgsIsHelpError"):
        never_raised = type("NoArgsIsHelpError", (Exception,), {})
        exceptions = types.SimpleNamespace(**vars(exceptions), NoArgsIsHelpError=never_raised)
    return exceptions


if __name__ == "__main__":
    main()
