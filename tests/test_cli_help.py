"""Every `--help` reads right at 80 and 120 columns: every word of the command's docstring and of
each option's help comes out as written (no markup accident: Rich once turned `--times A:B:N` into
`A🅱N`; nothing cut with "…"; hard-wrapped docstrings rewrapped, not ragged), no line is wider
than the terminal, flags show no type, argument names are upper case, and the commands are listed
in the README's order with the benchmarks after them."""

from __future__ import annotations

import re

import pytest
import typer

from radfield.cli.main import app, command_names

COMMAND = typer.main.get_command(app)
WIDTHS = (80, 120)


def words(text: str) -> str:
    return " ".join(text.replace("\b", " ").split())


def help_of(cli, monkeypatch, width: int, *args: str) -> str:
    monkeypatch.setenv("COLUMNS", str(width))
    code, out, err = cli(*args, "--help")
    assert code == 0 and err == "", err
    return out


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("name", command_names(app))
def test_every_help_text_comes_out_whole(cli, monkeypatch, name, width):
    out = help_of(cli, monkeypatch, width, name)
    command = COMMAND.commands[name]
    shown = words(out)
    assert words(command.help) in shown, f"{name}: the docstring is not shown as written"
    for param in command.params:
        if param.help and not param.hidden:
            assert words(param.help) in shown, f"{name} {param.name}: its help is not shown as written"
    assert all(len(line) <= width for line in out.splitlines()), f"{name}: a line is wider than {width} columns"
    assert "…" not in out and "<bool>" not in out
    assert not re.search("[\U0001F000-\U0001FAFF]", out), f"{name}: an emoji in the help"
    usage = out.splitlines()[0]
    assert usage.startswith(f"Usage: radfield {name} [OPTIONS]"), usage
    arguments = usage.split("[OPTIONS]", 1)[1]
    assert arguments == arguments.upper() and "..." not in arguments.replace("}...", "}"), usage   # NAME, not {name}


def test_the_root_help_lists_the_commands_then_the_benchmarks(cli, monkeypatch):
    out = help_of(cli, monkeypatch, 80)
    listed = [line.split()[0] for line in out.splitlines() if re.match(r"^  [a-z][a-z-]+  ", line)]
    assert listed == ["reconstruct", "import", "info", "render", "eval", "bake", "edit", "animate", "export", "view", "demo-scene",
                      "bench-quality", "bench-render", "bench-train", "bench-web", "bench-dist", "bench-startup"]
    assert out.index("Commands:") < out.index("reconstruct") < out.index("Benchmarks:") < out.index("bench-quality")
    assert "..." not in out.split("Commands:")[1] and all(len(line) <= 80 for line in out.splitlines())


def test_reconstruct_help_names_every_stage_in_order(cli, monkeypatch):
    from radfield.stages.registry import stages

    out = words(help_of(cli, monkeypatch, 120, "reconstruct"))
    assert " → ".join(stage.name for stage in stages()) in out
