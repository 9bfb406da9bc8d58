"""Progress on stderr (util/progress.py): a bar on a terminal, and when the output is a file or a
pipe a plain line each tenth of the way, never a blank line; nothing on stdout, whatever happens."""

from __future__ import annotations

import io
import re

from radfield.util.progress import LineProgress, progress_bar

LINE = re.compile(r"^(?P<what>[^:]+): (?P<pct>\d+)% \((?P<done>\d+)/(?P<total>\d+)\)(, .*)?, "
                  r"\d+:\d\d:\d\d elapsed(, \d+:\d\d:\d\d left)?$")


def test_a_task_is_a_line_each_tenth_of_the_way():
    stream = io.StringIO()
    with LineProgress(stream) as progress:
        task = progress.add_task("rendering 37 views", total=37)
        for _ in range(37):
            progress.advance(task)
        later = progress.add_task("refining", total=None)   # no total yet: nothing to say
        progress.update(later, completed=3)
        progress.update(later, total=6, completed=6, stats="loss 0.1")
    lines = stream.getvalue().splitlines()
    assert all(LINE.match(line) for line in lines), lines
    percents = [int(LINE.match(line)["pct"]) for line in lines if line.startswith("rendering")]
    assert percents == sorted(percents) and len(percents) == 10 and percents[-1] == 100
    assert lines[-1].startswith("refining: 100% (6/6), loss 0.1, ") and "left" not in lines[-1]
    assert "" not in lines


def test_a_resumed_task_starts_where_it_was():
    stream = io.StringIO()
    progress = LineProgress(stream)
    task = progress.add_task("training", total=100, completed=60)
    progress.update(task, completed=65)
    assert stream.getvalue() == ""            # 60 % was reached before: the next line is at 70 %
    progress.update(task, completed=70)
    assert stream.getvalue().startswith("training: 70% (70/100)")


def test_quiet_and_non_terminal_outputs(capsys):
    with progress_bar(True) as progress:
        progress.advance(progress.add_task("quiet", total=2), 2)
    with progress_bar(False) as progress:   # pytest's captured stderr is not a terminal
        assert isinstance(progress, LineProgress)
        progress.advance(progress.add_task("loud", total=2), 2)
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("loud: 100% (2/2)") and err.count("\n") == 1


def test_a_reconstruction_writes_progress_lines_to_a_file(cli, tmp_path):
    from radfield.demo.static import generate_scene

    data = generate_scene("blobs", tmp_path / "blobs", n_train=4, n_test=1, size=16, seed=0)
    code, out, err = cli("reconstruct", data, "-o", tmp_path / "run", "--iterations", "20", "--no-cage",
                         "--set", "init.num_points=50")
    assert code == 0 and "held-out PSNR" in out and "%" not in out
    lines = err.splitlines()
    assert "" not in lines and "\x1b" not in err   # no blank line, no cursor movement
    training = [line for line in lines if line.startswith("training: ")]
    assert len(training) == 10 and training[-1].startswith("training: 100% (20/20), loss "), training


def test_a_dynamic_scenes_hull_shows_its_carving(cli, tmp_path):
    """The envelope of a dynamic scene carves a hull per moment (109 s for smoke, shown only as
    "envelope: running" before): its loading and carving are progress lines."""
    code, _, err = cli("demo-scene", "smoke", "-o", tmp_path / "smoke", "--size", "16", "--times", "2",
                       "--train-views", "3", "--test-views", "1", "-q")
    assert code == 0, err
    code, _, err = cli("reconstruct", tmp_path / "smoke", "-o", tmp_path / "run", "--until", "envelope")
    assert code == 0, err
    assert "loading 6 training masks: 100% (6/6)" in err and "carving 2 moments' hulls: 100% (6/6)" in err, err


def test_the_terminal_bar_says_which_time_is_elapsed_and_which_left():
    """On a terminal (rich): "0:00:01 elapsed, 0:00:04 left" as the plain lines word it, the time
    left only where the task has a total (rich's bare columns read "0:00:01 left 0:00:04")."""
    from rich.console import Console

    from radfield.util.progress import _rich_bar

    bar = _rich_bar(stats=False)
    bar.update(bar.add_task("training", total=100), completed=5)
    bar.add_task("refining", total=None)
    console = Console(force_terminal=False, width=120, record=True)
    console.print(bar.make_tasks_table(bar.tasks))
    training, refining = console.export_text().splitlines()
    assert re.search(r"\d+:\d\d:\d\d elapsed, (-:--:--|\d+:\d\d:\d\d) left$", training.rstrip()), training
    assert refining.rstrip().endswith(" elapsed"), refining
