"""Every example the docs print runs (issue #28: the README's simulation example failed as printed).

The YAML examples (edit, animation and simulation specs) of docs/usage.md and README.md are found
in the text — indented blocks and ```yaml fences that start with `operations:`, `animate:` or
`simulate:`, and the `printf '…' > file.yaml` lines — and each is run with `radfield edit` /
`radfield animate` on a tiny run (20 primitives, a 48-tet box cage, 24×24 views). Templates name
their values with placeholders (`[rx, ry, rz]`, `SELECTION`, `OTHER_RUN_OR_MODEL`): PLACEHOLDERS
gives each a value, and a placeholder without one fails the test, as does an example that fails.

The command examples (```sh fences and the README's table) that use the demo paths (`demo/blobs`,
`demo/run`, …) run as printed, in order, in an empty folder, except the ones SKIPPED names with
the reason (full-size reconstructions, benchmarks, a server); templates with placeholders
(`RUN`, `DATA`, `OUT`) are not commands. The demo run itself is made cheaper than the printed
command (CHEAP_RUN: 300 primitives, 30 steps), and so is the dynamic demo (CHEAPER: a 16 px smoke scene of 4
cameras × 3 moments, a cage-less 30-step run): the commands after them read them as they would the
full ones.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from radfield.core.geometry.cage import write_cage

ROOT = Path(__file__).resolve().parents[1]
DOCS = ("README.md", "docs/usage.md")
SPEC_KEYS = ("operations:", "animate:", "simulate:")

# the values of the templates' placeholders ({...} filled in per test: paths)
PLACEHOLDERS = {
    "[rx, ry, rz]": "[10, 0, 30]", "[tx, ty, tz]": "[0.1, 0, 0]", "scale: s": "scale: 1.2",
    "[x, y, z]": "[0.2, 0.2, 0.2]", "radius: r": "radius: 0.4", "[x0, y0, z0]": "[-0.5, -0.5, -0.5]",
    "[x1, y1, z1]": "[0.5, 0.5, 0.5]", "center: [...]": "center: [0, 0, 0]", "size: [...]": "size: [0.6, 0.6, 0.6]",
    "point: [...]": "point: [0, 0, 0.3]", "normal: [...]": "normal: [0, 0, 1]", "[r, g, b]": "[1, 0.5, 0.5]",
    "SELECTION": "{sphere: {center: [0, 0, 0], radius: 0.5}}", "edge_length: L": "edge_length: 0.5",
    "simulate: {...}": "simulate: {frames: 3}",
    "OTHER_RUN_OR_MODEL": "{run}", "POSED_DATASET": "{data}", "moved_cage.vtk": "{moved}", "cutter.stl": "{cutter}",
    "frames/*.vtk": "{frames}",
}
LEFTOVER = re.compile(r"\b(rx|ry|rz|tx|ty|tz|x0|y1|[A-Z][A-Z_]{2,})\b|\[\.\.\.\]|\{\.\.\.\}")


def _doc_text(name: str) -> str:
    return (ROOT / name).read_text(encoding="utf-8")


def spec_examples() -> list[tuple[str, str]]:
    """(where, YAML text) of every spec example of the docs; an "instead of" line of a block is
    an alternative to the line above it, so such a block gives one example per alternative."""
    found = []
    for name in DOCS:
        lines = _doc_text(name).splitlines()
        i = 0
        while i < len(lines):
            line = lines[i]
            start = None
            if line.startswith("    ") and line.strip().startswith(SPEC_KEYS) and not lines[i - 1].strip():
                start, indent = i, 4
            elif line.strip() == "```yaml":
                start, indent, i = i + 1, 0, i + 1
            if start is None:
                for m in re.finditer(r"printf '([^']*)' > (\S+\.yaml)", line):
                    found.append((f"{name}:{i + 1}", m.group(1).replace("\\n", "\n")))
                i += 1
                continue
            block = []
            while i < len(lines) and lines[i].strip() and lines[i].strip() != "```" and \
                    (indent == 0 or lines[i].startswith(" " * indent)):
                block.append(lines[i][indent:])
                i += 1
            where = f"{name}:{start + 1}"
            alternatives = [k for k, b in enumerate(block) if "# instead of" in b]
            if alternatives:
                base = [b for k, b in enumerate(block) if k not in alternatives]
                found.append((where, "\n".join(base)))
                for k in alternatives:   # the alternative replaces the pose source above it
                    found.append((f"{where} (alternative)", block[k].split("#")[0]))
            else:
                found.append((where, "\n".join(block)))
    return found


def command_examples() -> list[tuple[str, str]]:
    """(where, command) of every `radfield …` and `printf … > demo/…` line of the docs' sh fences
    and of the README's table, in the order of the text (usage.md first: it makes the demo run)."""
    found = []
    for name in reversed(DOCS):
        text = _doc_text(name)
        for m in re.finditer(r"```sh\n(.*?)```", text, re.S):
            first = text[: m.start()].count("\n") + 2
            for k, line in enumerate(m.group(1).splitlines()):
                line = line.split("  #")[0].strip()
                if line.startswith(("radfield ", "printf ")):
                    found.append((f"{name}:{first + k}", line))
        for m in re.finditer(r"\| `(radfield [^`]*)`( \(with `(printf [^`]*)`\))? \|", text):
            where = f"{name}:{text[: m.start()].count(chr(10)) + 1}"
            if m.group(3):
                found.append((where, m.group(3)))
            for part in m.group(1).split(" && "):
                found.append((where, part))
    return found


# --- a tiny run for the spec examples ---------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny(tmp_path_factory, hand_run):
    root = tmp_path_factory.mktemp("docs")
    data, run, v, t = hand_run(root, half=0.55)   # the cage above the docs' `ground: -0.6`
    write_cage(root / "moved", v * [1.1, 1.0, 0.9], t)
    for k in range(3):
        write_cage(root / "frames" / f"frame_{k}", v + [0.0, 0.0, 0.05 * k], t)
    import trimesh
    trimesh.creation.box(extents=[0.5, 0.5, 0.5]).export(root / "cutter.stl")
    paths = {"run": run, "data": data, "moved": root / "moved" / "cage.vtk", "cutter": root / "cutter.stl",
             "frames": root / "frames" / "*" / "cage.npz"}
    return root, paths


def test_the_docs_print_the_spec_examples_this_test_knows():
    """The extraction finds what the docs print (an empty list would pass everything below)."""
    examples = spec_examples()
    texts = "\n".join(text for _, text in examples)
    for needed in ("twist:", "bend:", "taper:", "deform:", "boolean:", "compose:", "recolor:", "transfer:", "remesh:",
                   "youngs_modulus: 1e6", "animate: {cages:", "simulate: {frames: 30}"):
        assert needed in texts, needed
    commands = " ; ".join(c for _, c in command_examples())
    for needed in ("radfield animate demo/run --simulate demo/fall.yaml", "radfield info demo/run --json",
                   "radfield export demo/run --format ply-3dgs"):
        assert needed in commands, needed


def _fill(text: str, paths: dict) -> str:
    for key, value in PLACEHOLDERS.items():
        for name, path in paths.items():
            value = value.replace("{" + name + "}", str(path))
        text = text.replace(key, value)
    return text


@pytest.mark.parametrize("where, text", spec_examples(), ids=lambda x: str(x).split("\n")[0][:60])
def test_every_spec_example_runs(cli, tiny, tmp_path, where, text):
    root, paths = tiny
    filled = _fill(text, paths)
    left = LEFTOVER.search(re.sub(r"#.*", "", filled))
    assert left is None, f"{where}: placeholder {left.group(0)!r} has no value in PLACEHOLDERS"
    data = yaml.safe_load(filled)
    if "operations" in data:
        # one edit per operation, so that a failure names its line (and one cut cannot empty the next)
        for k, op in enumerate(data["operations"]):
            spec = tmp_path / f"op{k}.yaml"
            spec.write_text(yaml.safe_dump({"operations": [op]}))
            code, _, err = cli("edit", paths["run"], "--spec", spec, "-o", tmp_path / f"out{k}", "-q")
            assert code == 0, f"{where}: {op}: {err}"
        return
    spec = tmp_path / "spec.yaml"
    spec.write_text(filled + "\n")    # the text as printed: the loader must read 1e6 as a number
    if set(data) == {"simulate"}:
        code, _, err = cli("animate", paths["run"], "--simulate", spec, "-o", tmp_path / "out", "-q")
    else:
        code, _, err = cli("animate", paths["run"], "--spec", spec, "-o", tmp_path / "out", "-q")
    assert code == 0, f"{where}: {err}"
    assert (tmp_path / "out" / "animation.mp4").is_file()


# --- the command examples on the demo scene ---------------------------------------------------------

CHEAP_RUN = ["--iterations", "30", "--set", "init.num_points=300"]
CHEAPER = {   # the start of a printed command -> what this test adds to it
    "demo-scene smoke -o demo/smoke": ["--size", "16", "--times", "3", "--train-views", "4", "--test-views", "2"],
    "reconstruct demo/smoke -o demo/smoke-run": ["--no-cage", *CHEAP_RUN],
    "import demo/model.ply -o demo/imported": ["--views", "12", "--size", "64"],
}
SKIPPED = {   # the start of a command -> why it does not run here
    "radfield reconstruct demo/blobs -o demo/run --iterations 6000": "continues training to 6000 steps (minutes)",
    "radfield reconstruct demo/blobs -o demo/gauss": "a second reconstruction (test_pipeline covers --primitive gaussian)",
    "radfield eval demo/run demo/gauss --compare": "needs demo/gauss (test_report covers --compare)",
    "radfield reconstruct ../shared/datasets/fox_small": "the full-size fox capture (9 min; test_sfm covers photos)",
    "radfield view": "a server that runs until stopped (test_web and test_viewer open it in a browser)",
    "radfield bench-": "benchmarks take minutes (test_bench runs them at tiny sizes)",
    "radfield demo-scene studio": "another demo scene (test_datasets generates every scene)",
    "radfield demo-scene glossy": "another demo scene (test_datasets generates every scene)",
}


def test_the_command_examples_run_as_printed(cli, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    done, seen = [], set()
    for where, command in command_examples():
        if command in seen:
            continue
        seen.add(command)
        if any(command.startswith(s) for s in SKIPPED):
            continue
        words = shlex.split(command)
        if any(re.fullmatch(r"[A-Z][A-Z0-9_]*", w) for w in words):   # a template (RUN, DATA, S), not a command
            continue
        if words[0] == "printf":
            path = Path(words[-1])
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(words[1].replace("\\n", "\n"))
            continue
        args = words[1:]
        if "-o" in args and args[0] != "reconstruct" and Path(args[args.index("-o") + 1]).exists():
            # the two documents print independent examples, some with the same output (demo/rotated)
            out = Path(args[args.index("-o") + 1])
            shutil.rmtree(out) if out.is_dir() else out.unlink()
        if args[:4] == ["reconstruct", "demo/blobs", "-o", "demo/run"] and len(args) == 4:
            args += CHEAP_RUN
        args += next((extra for start, extra in CHEAPER.items() if " ".join(args).startswith(start)), [])
        code, _, err = cli(*args)
        assert code == 0, f"{where}: {command}: {err}"
        done.append(command)
    # what ran: the set-up, every command on the demo run, the edits and the simulation
    assert any(c.startswith("radfield animate demo/run --simulate") for c in done)
    assert len(done) >= 12, done
    assert np.isfinite(json.loads(Path("demo/fall/animation.json").read_text())["consecutive_psnr"])
