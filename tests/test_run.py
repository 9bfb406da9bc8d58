"""radfield.run.Run, the one place that knows a run directory's layout: the products of a real
reconstruction and of an edited run are where it says, the products it names are
the ones the stages write, a folder that is not a run is one line, and the module stays light to import."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from radfield import run as layout
from radfield.errors import RadfieldError
from radfield.pipeline.config import load_config, run_config
from radfield.stages.registry import stages
from radfield.pipeline.runner import run_pipeline
from radfield.run import Run, model_file

CONFIG = ["init.num_points=120", "envelope.target_faces=200", "train.iterations=3"]


@pytest.fixture(autouse=True, scope="module")
def torch_kernels():
    """The readable torch kernels: these tests check where files are, not how fast they are made."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RADFIELD_KERNELS", "torch")
        yield


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """(dataset, run) of a real reconstruction of a tiny scene, with envelope, cage and binding."""
    from radfield.demo.static import generate_scene

    root = tmp_path_factory.mktemp("run")
    scene = generate_scene("blobs", root / "blobs", n_train=6, n_test=2, size=24)
    run_pipeline(stages(), root / "run", load_config(sets=CONFIG), input_path=scene, until_stage="bind", quiet=True)
    return scene, root / "run"


def test_a_reconstructed_run(made):
    scene, run_dir = made
    run = Run.open(run_dir)
    assert run.exists and not run.is_edited
    assert run.model == run.trained_model == run_dir / "train" / "model.safetensors" and run.model.is_file()
    assert run.cage == run.reconstructed_cage == run_dir / "tetra" / "cage.npz" and run.cage.is_file()
    assert run.binding == run_dir / "bind" / "model_binding.npz"
    assert run.scene.is_file() and run.envelope.is_file()
    assert run.dataset() == run.input == scene.resolve()      # a posed dataset: the run's input
    assert not run.normalization.exists() and not run.checkpoint.exists()   # no photos, no interrupted training
    assert run.manifest("train")["figures"]["iterations"] == 3 and run.manifest("eval") is None
    assert run.stage_names() == load_config()["stages"]
    assert run_config(run)["init"]["num_points"] == 120 and run_config(run, {"seed": 7})["seed"] == 7
    assert run.marker()["input"] == str(scene.resolve())
    assert not run.scratch() and not run.work_dir("train").exists()    # a finished run leaves none
    with np.load(run.binding) as binding:
        assert (binding["tet"] >= 0).any()
    assert model_file(run_dir) == run.model and model_file(run.model) == run.model


def test_every_product_run_names_is_an_output_of_its_stage(made):
    """Run builds the paths; the stages declare their outputs with Run's names (they import them):
    a stage that stopped writing a product commands read fails here."""
    outputs = {stage.name: stage.outputs for stage in stages()}
    for stage, name in [(layout.SFM_STAGE, layout.SFM_DATASET), (layout.DATA_STAGE, layout.SCENE_FILE),
                        (layout.ENVELOPE_STAGE, layout.ENVELOPE_FILE), (layout.CAGE_STAGE, layout.CAGE_FILE),
                        (layout.MODEL_STAGE, layout.MODEL_FILE), (layout.BIND_STAGE, layout.BINDING_FILE),
                        (layout.EVAL_STAGE, layout.METRICS_FILE)]:
        assert name in outputs[stage], (stage, name)
        if stage not in (layout.SFM_STAGE, layout.EVAL_STAGE):   # not applicable to a posed dataset; not run
            assert (made[1] / stage / name).exists(), (stage, name)


def test_an_edited_run(made, cli, tmp_path):
    scene, run_dir = made
    code, _, err = cli("edit", run_dir, "-o", tmp_path / "edited", "--translate", "0.1,0,0", "-q")
    assert code == 0, err
    run = Run.open(tmp_path / "edited")
    assert run.is_edited and run.model == run.edit_dir / "model.safetensors" and run.model.is_file()
    assert run.cage == run.edit_dir / "cage.npz" and run.binding == run.edit_dir / "model_binding.npz"
    assert not run.trained_model.exists() and not run.reconstructed_cage.exists()
    assert run.edit_spec.is_file() and run.manifest("edit")["figures"]["operations"] == 1
    assert run.dataset() == scene.resolve()   # the source run's dataset, for render and eval
    assert run.marker()["edited_from"] == str(run_dir.resolve())
    assert run.config_file.read_text() == Run(run_dir).config_file.read_text()
    assert run.stage_names()[-1] == "edit"
    # edited from a model file: no config, no dataset, no cage
    code, _, err = cli("edit", Run(run_dir).model, "-o", tmp_path / "from_model", "--scale", "1.1", "-q")
    assert code == 0, err
    bare = Run.open(tmp_path / "from_model")
    assert bare.is_edited and bare.dataset() is None and bare.cage is None and not bare.config_file.exists()
    assert run_config(bare) == load_config()


def test_info_and_the_viewer_of_an_edited_run(made, cli, tmp_path):
    """`info` shows the edit (its spec, when, edited_from), not the reconstruction's stages as "not
    run"; the viewer shows the source run's dataset cameras (an edited run has no data stage)."""
    import torch

    from radfield.delivery.view_scene import viewer_scene

    scene, run_dir = made
    edited, again = tmp_path / "edited", tmp_path / "again"
    assert cli("edit", run_dir, "-o", edited, "--translate", "0.1,0,0", "-q")[0] == 0
    assert cli("edit", edited, "-o", again, "--scale", "1.1", "-q")[0] == 0
    code, out, err = cli("info", edited, "--json")
    assert code == 0, err
    info = json.loads(out)
    assert list(info["stages"]) == ["edit"] and info["stages"]["edit"]["done"]
    assert info["edited_from"] == str(run_dir.resolve())
    assert info["edit"]["operations"] == [{"transform": {"select": "all", "translate": [0.1, 0.0, 0.0]}}]
    assert info["edit"]["created"] and info["edit"]["spec"] == str((edited / "edit" / "spec.yaml").resolve())
    code, text, err = cli("info", edited)
    assert code == 0 and "not run" not in text, text
    assert f"edited from: {run_dir.resolve()}" in text and "1. transform {select: all, translate: [0.1, 0.0, 0.0]}" in text
    plain = json.loads(cli("info", run_dir, "--json")[1])   # a reconstructed run: the keys, null
    assert plain["edited_from"] is None and plain["edit"] is None and "edit" not in plain["stages"]

    # the viewer: the source's cameras, through an edit of an edit too
    assert Run(again).source_run().path == run_dir.resolve() and Run(again).dataset_scene() == Run(run_dir).scene
    source = viewer_scene(run_dir)
    assert len(source.cameras) == 8
    for view in (viewer_scene(edited), viewer_scene(again)):
        assert len(view.cameras) == len(source.cameras)
        assert all(torch.equal(a.c2w, b.c2w) for a, b in zip(view.cameras, source.cameras))
    # a run edited from a model file has no dataset: no cameras, no error
    assert cli("edit", Run(run_dir).model, "-o", tmp_path / "bare", "--scale", "1.1", "-q")[0] == 0
    assert viewer_scene(tmp_path / "bare").cameras == [] and Run(tmp_path / "bare").source_run() is None


def test_a_run_made_before_the_bind_stage_keeps_its_binding_in_train(tmp_path):
    (tmp_path / "train").mkdir()
    (tmp_path / layout.RUN_MARKER).write_text(json.dumps({"kind": "radfield-run", "input": None}))
    assert Run(tmp_path).binding is None
    (tmp_path / "train" / layout.BINDING_FILE).write_bytes(b"")
    assert Run(tmp_path).binding == tmp_path / "train" / layout.BINDING_FILE


def test_a_folder_that_is_not_a_run_is_one_line(tmp_path, cli):
    with pytest.raises(RadfieldError) as error:
        Run.open(tmp_path)
    assert str(error.value) == f"{tmp_path} is not a radfield run directory" and "\n" not in str(error.value)
    assert not Run(tmp_path).exists
    with pytest.raises(RadfieldError, match="run directory has no trained model yet"):
        model_file(tmp_path)
    code, out, err = cli("info", tmp_path)
    assert code == 1 and out == "" and err == f"radfield: error: {tmp_path} is not a radfield run directory\n"
    (tmp_path / layout.RUN_MARKER).write_text("{not json")
    with pytest.raises(RadfieldError, match="damaged radfield-run.json"):
        Run.open(tmp_path).marker()


def test_the_run_module_is_light():
    code = ("import sys; from radfield.run import Run; Run('x').model; "
            "print(sorted({m.partition('.')[0] for m in sys.modules} & {'torch', 'numpy', 'yaml', 'rich'}))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == "[]", done.stderr
