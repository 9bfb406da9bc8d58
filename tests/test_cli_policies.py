"""The command-line policies every command shares (issue #28, "What a new user tripped over"):
one output policy (an existing non-empty output is refused unless --force, a run directory never
written into), one name per meaning of --split, real defaults in --help."""

from __future__ import annotations

import json

import pytest



@pytest.fixture(scope="module")
def scene(tmp_path_factory, hand_run):
    """(dataset, run): a 24×24 blobs dataset and a run of 20 random primitives with a cage and a
    binding, made by hand (the policies are checked, not the reconstruction)."""
    data, run, _, _ = hand_run(tmp_path_factory.mktemp("policies"))
    return data, run


def _snapshot(folder):
    return {p.relative_to(folder): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


# every command that writes, with OUT its output ({out}) and what it needs to get that far
COMMANDS = {
    "render": (["render", "{run}", "-o", "{out}", "-q"], "folder"),
    "render --video": (["render", "{run}", "-o", "{new}", "--video", "{out}", "--orbit", "2", "-q"], "file"),
    "eval": (["eval", "{run}", "-o", "{out}", "-q"], "folder"),
    "eval --compare": (["eval", "--compare", "{run}", "{run}", "-o", "{out}", "-q"], "folder"),
    "edit": (["edit", "{run}", "-o", "{out}", "--scale", "1.1", "-q"], "folder"),
    "animate": (["animate", "{run}", "--simulate", "{sim}", "-o", "{out}", "-q"], "folder"),
    "bake": (["bake", "{run}", "-o", "{out}", "-q"], "file"),
    "export": (["export", "{run}", "--format", "points", "-o", "{out}"], "file"),
    "demo-scene": (["demo-scene", "blobs", "-o", "{out}", "--size", "16"], "folder"),
}


def _args(template, scene, tmp_path, out):
    data, run = scene
    sim = tmp_path / "sim.yaml"
    sim.write_text("simulate: {frames: 2}\n")
    return [a.format(run=run, out=out, new=tmp_path / "new", sim=sim) for a in template]


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_refuses_an_existing_output_without_force(cli, scene, tmp_path, command):
    template, kind = COMMANDS[command]
    if kind == "folder":
        out = tmp_path / "out"
        out.mkdir()
        (out / "keep.txt").write_text("the user's")
    else:
        out = tmp_path / ("out.mp4" if "--video" in template else "out.ply" if command == "export" else "out.safetensors")
        out.write_bytes(b"the user's")
    before = _snapshot(tmp_path)
    code, _, err = cli(*_args(template, scene, tmp_path, out))
    assert code == 1, err
    assert err.startswith("radfield: error: ") and err.count("\n") == 1, err
    assert "already exists" in err and "--force" in err, err
    assert _snapshot(tmp_path) == {**before, **{k: v for k, v in _snapshot(tmp_path).items() if k.name == "sim.yaml"}}


@pytest.mark.parametrize("command", ["render", "eval", "eval --compare", "edit", "animate", "bake", "export"])
def test_no_command_writes_into_a_run_directory_even_with_force(cli, scene, tmp_path, command):
    """`eval X -o RUN` used to drop report files into the run; outputs inside a run are refused too."""
    data, run = scene
    template, kind = COMMANDS[command]
    out = run if kind == "folder" else run / "train" / ("out.ply" if command == "export" else "out.safetensors")
    before = _snapshot(run)
    for target in ([out, run / "frames"] if kind == "folder" else [out]):
        code, _, err = cli(*_args(template, scene, tmp_path, target), "--force")
        assert code == 1, err
        assert err.count("\n") == 1 and "run directory" in err and "never into it" in err, err
    assert _snapshot(run) == before


def test_force_writes_into_an_existing_folder_and_keeps_the_rest(cli, scene, tmp_path):
    data, run = scene
    out = tmp_path / "frames"
    out.mkdir()
    (out / "keep.txt").write_text("the user's")
    code, _, err = cli("render", run, "-o", out, "-q", "--force")
    assert code == 0, err
    assert (out / "keep.txt").read_text() == "the user's" and len(list(out.glob("*.png"))) == 2
    # an empty existing folder needs no --force (edit used to refuse it)
    (tmp_path / "empty").mkdir()
    code, _, err = cli("edit", run, "-o", tmp_path / "empty", "--scale", "1.1", "-q")
    assert code == 0, err
    assert (tmp_path / "empty" / "edit" / "model.safetensors").is_file()
    # but an edited run is a run: never replaced, even with --force
    code, _, err = cli("edit", run, "-o", tmp_path / "empty", "--scale", "1.2", "-q", "--force")
    assert code == 1 and "run directory" in err


def test_bake_force_replaces_the_file(cli, scene, tmp_path):
    data, run = scene
    out = tmp_path / "baked.safetensors"
    out.write_bytes(b"old")
    code, _, err = cli("bake", run, "-o", out, "-q", "--force")
    assert code == 0, err
    assert out.read_bytes() != b"old"


def test_demo_scene_exist_ok_and_force(cli, tmp_path):
    out = tmp_path / "blobs"
    code, _, err = cli("demo-scene", "blobs", "-o", out, "--size", "16", "--train-views", "2", "--test-views", "1")
    assert code == 0, err
    code, stdout, err = cli("demo-scene", "blobs", "-o", out, "--size", "16", "--exist-ok")
    assert code == 0 and "already holds" in stdout, err
    code, _, err = cli("demo-scene", "blobs", "-o", out, "--size", "16", "--seed", "3")
    assert code == 1 and "already exists" in err and "--force" in err
    # another scene's folder: said so, and never mixed, not even with --force (objects over blobs kept
    # blobs' mesh.ply, which the envelope stage then read as the objects' surface)
    for args in ([], ["--exist-ok"], ["--force"]):
        code, _, err = cli("demo-scene", "objects", "-o", out, "--size", "16", *args)
        assert code == 1 and err == f"radfield: error: {out}: holds the blobs demo scene, not objects; write objects " \
                                    "to another folder\n", err
    assert json.loads((out / "scene.json").read_text())["name"] == "blobs"
    other = tmp_path / "mine"
    other.mkdir()
    (other / "keep.txt").write_text("the user's")
    code, _, err = cli("demo-scene", "checker", "-o", other, "--size", "16", "--train-views", "2", "--test-views", "1", "--force")
    assert code == 0, err
    assert json.loads((other / "scene.json").read_text())["name"] == "checker" and (other / "keep.txt").is_file()


def test_split_means_a_dataset_split_and_split_threshold_the_edit_threshold(cli, scene, tmp_path):
    data, run = scene
    code, stdout, _ = cli("edit", "--help")
    assert "--split-threshold" in stdout and "--split " not in stdout.replace("--split-threshold", "")
    for command in ("render", "eval", "animate", "bake"):
        code, stdout, _ = cli(command, "--help")
        assert "--split " in stdout or "--split  " in stdout, command
    code, _, err = cli("edit", run, "-o", tmp_path / "a", "--scale", "1.1", "--split-threshold", "0", "-q")
    assert code == 0 and err == "", err
    assert json.loads((tmp_path / "a" / "edit" / "manifest.json").read_text())["options"]["split"] is None
    # the old name still works for one release, with a one-line note
    code, _, err = cli("edit", run, "-o", tmp_path / "b", "--scale", "1.1", "--split", "0.3", "-q")
    assert code == 0, err
    assert err.count("\n") == 1 and "deprecated" in err and "--split-threshold" in err
    assert json.loads((tmp_path / "b" / "edit" / "manifest.json").read_text())["options"]["split"] == 0.3
    code, _, err = cli("edit", run, "-o", tmp_path / "c", "--scale", "1.1", "--split-threshold", "-1")
    assert code == 1 and "--split-threshold must be at least 0, got -1" in err


@pytest.mark.parametrize("command", ["render", "animate"])
def test_fps_help_shows_the_real_default(cli, command):
    code, stdout, _ = cli(command, "--help")
    text = " ".join(stdout.replace("│", " ").split())
    assert "default: 0.0" not in text
    assert "[default: (30, or the" in text, text
