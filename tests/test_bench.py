"""The benchmark commands (radfield.bench, radfield/cli/bench.py): each runs on a tiny
configuration and prints every figure it promises. What the figures are is measured by running
them, not asserted here."""

import pytest


def test_bench_render_prints_each_kind_and_the_ratio(cli):
    code, out, err = cli("bench-render", "--primitives", "200", "--width", "32", "--height", "24", "--views", "1",
                         "--repeats", "1", "--baseline")
    assert code == 0, err
    for kind in ("neural", "neural-hard", "gaussian"):
        assert any(line.split()[:1] == [kind] for line in out.splitlines()), (kind, out)
    assert "neural/gaussian time ratio" in out
    code, _, err = cli("bench-render", "--primitives", "0")
    assert code == 1 and err.startswith("radfield: error:")


def test_bench_render_profile_prints_each_kinds_top_costs(cli):
    code, out, err = cli("bench-render", "--primitives", "100", "--width", "16", "--height", "16", "--views", "1",
                         "--repeats", "1", "--profile")
    assert code == 0, err
    for kind in ("neural", "neural-hard", "gaussian"):
        assert f"top costs, {kind}, one forward+backward, by host time:" in out
    assert "by device time" not in out and "kernel launches" not in out   # the CPU has neither
    assert "Profiler clears events" not in err   # torch 2.11's warning about cycles (there is one)


def test_bench_train_prints_every_part(cli):
    code, out, err = cli("bench-train", "--primitives", "300", "--sizes", "32", "--steps", "1", "--quiet", "--baseline")
    assert code == 0, err
    header = next(line for line in out.splitlines() if "forward" in line and "population" in line)
    rows = [line.split() for line in out.splitlines() if line.split()[:1] in (["neural"], ["gaussian"])]
    ratios = [line.split() for line in out.splitlines() if line.split()[:1] == ["x"]]
    assert len(rows) == 4 and "train()" in header and "peak MiB" in header and [r[3] for r in rows] == ["torch", "fused"] * 2
    for row in rows:   # kind, count, size, path, 5 parts, sum, train(), setup, Mpairs/s, peak MiB
        parts = [float(x) for x in row[4:9]]
        assert row[1] == "300" and row[2] == "32x32" and all(p >= 0 for p in parts)
        # every figure is printed to 0.1 ms: six roundings of up to 0.05 each separate the sum from its parts
        assert float(row[9]) == pytest.approx(sum(parts), abs=0.3 + 1e-9) and float(row[10]) > 0
        assert float(row[11]) > 0 and float(row[12]) >= 0   # loop.train's set-up, pairs per second
        assert 10 < float(row[13]) < 24 * 1024   # the process's resident memory at the steps' peak
    assert len(ratios) == 2 and all(len(r) == 8 and float(r[6]) > 0 for r in ratios)   # x, 5 parts, sum, train()
    code, _, err = cli("bench-train", "--sizes", "0")
    assert code == 1 and "radfield: error: --sizes" in err
    code, out, err = cli("bench-train", "--primitives", "300", "--sizes", "32", "--steps", "1", "--quiet",
                         "--kinds", "neural-hard")
    assert code == 0 and [line.split()[0] for line in out.splitlines()[2:]] == ["neural-hard"], err
    code, _, err = cli("bench-train", "--kinds", "neural,splat")
    assert code == 1 and "radfield: error: --kinds must be among neural, neural-hard, gaussian" in err


def test_bench_startup_prints_a_figure_per_command(cli):
    from radfield.cli.main import app, command_names

    code, out, err = cli("bench-startup", "--repeats", "1")
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0].startswith("bench-startup: median of 1 fresh processes each, target 0.5 s")
    for invocation in ["radfield --help"] + [f"radfield {name} --help" for name in command_names(app)]:
        assert sum(line.split()[:len(invocation.split())] == invocation.split() for line in lines) == 1, invocation
    assert f" of {len(command_names(app)) + 1} within 0.5 s" in lines[-1]
    code, _, err = cli("bench-startup", "--repeats", "0")
    assert code == 1 and err == "radfield: error: --repeats must be positive\n"
