"""The view-condition registry (radfield/conditions) is the one seam a new condition plugs into.

The test defines a condition of its own — an exposure value EV per frame, which brightens every
colour by EV · STEP — and a kind that reads it (neural primitives whose DC colour is offset by
it), registers both, and reconstructs, renders, evaluates and exports a dataset whose frames carry
an exposure through the project's own code paths, none of which is touched: the readers, the data
stage, `render`, `eval`, `export` and `info` only ask the registry. The built-in conditions (time,
light) then pass the same generic checks, and the checks the dynamic (test_dynamic_*.py) and the
relighting (test_relight_*.py) tests share are written here once, for each built-in condition
(CASES: what differs between them), their messages built from the condition's words.
"""

import contextlib
import io
import json
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import torch

from radfield import conditions
from radfield.conditions import Asked, Condition
from radfield.core import kinds
from radfield.core.geometry.cameras import Camera, Light, look_at
from radfield.core.kinds import random_neural
from radfield.core.kinds.neural import NeuralKind, NeuralPrimitives
from radfield.core.render.rasterize import render
from radfield.core.splat.sh import C0
from radfield.datasets.readers import load_dataset
from radfield.datasets.scene import load_scene, read_dataset, scene_from_json
from radfield.model_formats.ply_3dgs import read_gaussian_ply
from radfield.demo.olat import generate_olat
from radfield.demo.static import generate_scene
from radfield.demo.timelapse import generate_dynamic
from radfield.errors import RadfieldError
from radfield.model_file import load_model, save_model
from radfield.pipeline.config import load_defaults

from shared_helpers import frames, nerfstudio_copy, rewrite, with_network, with_time

STEP = 0.1                    # colour offset per exposure value
EXPOSURES = (-1.0, 0.0, 1.0)  # the frames' exposures, in turn


class Exposure(Condition):
    name, plural, unit, model_words, kind_words = "exposure", "exposures", "exposures", "exposure-varying", "exposure-conditioned"
    value_words, how, tag = "an exposure", "--at exposure=EV", "e"
    drawn, once, how_once = ("at", "exposure"), "one exposure", "--at exposure=EV"

    def from_json(self, value, where=""):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not -4.0 <= value <= 4.0:
            raise RadfieldError(f"{where}: 'exposure' must be a number in [-4, 4], not {value!r}")
        return float(value)

    def key(self, value):
        return value

    def ordered(self):
        return True


@dataclass
class ExposedPrimitives(NeuralPrimitives):
    kind = "neural-exposure"


class ExposureKind(NeuralKind):
    """Neural primitives drawn at an exposure: the DC colour offset by EV · STEP (no tensor of its own)."""

    name = "neural-exposure"
    primitives = ExposedPrimitives
    conditions = ("exposure",)

    def from_points(self, geometry, settings, seed):
        static = super().from_points(geometry, settings, seed)
        return ExposedPrimitives(**{f: getattr(static, f) for f in static.__dataclass_fields__})

    def at_view(self, prims, camera):
        return self.at_conditions(prims, {"exposure": camera.conditions["exposure"]})

    def at_conditions(self, prims, values):
        fields = {f: getattr(prims, f) for f in NeuralPrimitives.__dataclass_fields__}
        dc = prims.sh[:, :1] + values["exposure"] * STEP / C0
        return NeuralPrimitives(**{**fields, "sh": torch.cat([dc, prims.sh[:, 1:]], 1)})


@pytest.fixture
def exposure():
    condition, kind = conditions.register(Exposure()), kinds.register(ExposureKind())
    yield condition
    conditions.unregister(condition.name)
    kinds.unregister(kind.name)


@pytest.fixture(scope="module")
def exposed(tmp_path_factory) -> Path:
    """The blobs scene with an exposure on every frame: each image brightened by EV · STEP where
    the object is (alpha-weighted, as the renderer composites the offset colour)."""
    root = generate_scene("blobs", tmp_path_factory.mktemp("exposed") / "blobs", n_train=6, n_test=3, size=20,
                          mesh=False)
    k = 0
    for split in ("train", "test"):
        path = root / f"transforms_{split}.json"
        meta = json.loads(path.read_text())
        for frame in meta["frames"]:
            ev = EXPOSURES[k % len(EXPOSURES)]
            k += 1
            frame["exposure"] = ev
            image_path = next(root.glob(frame["file_path"].removeprefix("./") + ".*"))
            rgba = cv2.imread(str(image_path), cv2.IMREAD_UNCHANGED).astype(np.float64) / 255.0
            alpha = rgba[..., 3:]
            rgba[..., :3] = np.clip(rgba[..., :3] + ev * STEP * (alpha > 0), 0.0, 1.0)
            cv2.imwrite(str(image_path), np.round(rgba * 255.0).astype(np.uint8))
        path.write_text(json.dumps(meta, indent=1))
    return root


def test_a_condition_defined_here_goes_through_reconstruct_render_eval_and_export(cli, exposure, exposed, tmp_path):
    run = tmp_path / "run"
    code, out, err = cli("reconstruct", exposed, "-o", run, "--no-cage", "--iterations", "60", "-q")
    assert code == 0, err
    # the data stage counted the exposures; the views' condition chose the kind that reads it
    assert "exposure-varying scene: 3 exposures, " in out, out
    assert load_model(run / "train" / "model.safetensors").kind == "neural-exposure"
    scene = json.loads((run / "data" / "scene.json").read_text())
    assert [view["exposure"] for view in scene["splits"]["test"]] == [EXPOSURES[k % 3] for k in range(6, 9)]

    # eval: each test view drawn at its own exposure, the figures per exposure, a report section
    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    assert [row["exposure"] for row in metrics["per_exposure"]] == sorted(EXPOSURES)
    assert [v["exposure"] for v in metrics["per_view"]] == [EXPOSURES[k % 3] for k in range(6, 9)]
    assert "## Per exposure" in (run / "eval" / "report.md").read_text()
    code, out, err = cli("eval", run, "-o", tmp_path / "eval")
    assert code == 0 and "3 exposures: PSNR from " in out, err

    # render: the dataset's views at their own exposures, or every view at one (--at)
    assert cli("render", run, "-o", tmp_path / "own", "-q")[0] == 0
    assert cli("render", run, "-o", tmp_path / "bright", "--at", "exposure=1", "-q")[0] == 0
    assert cli("render", run, "-o", tmp_path / "dark", "--at", "exposure=-1", "-q")[0] == 0
    own = {p.name: cv2.imread(str(p)).astype(np.float64) for p in (tmp_path / "own").glob("*.png")}
    bright = {p.name: cv2.imread(str(p)).astype(np.float64) for p in (tmp_path / "bright").glob("*.png")}
    dark = {p.name: cv2.imread(str(p)).astype(np.float64) for p in (tmp_path / "dark").glob("*.png")}
    assert len(own) == 3 and bright.keys() == own.keys() == dark.keys()
    name_at_1 = sorted(own)[2]   # test views 6, 7, 8 have exposures 1, -1, 0
    assert np.array_equal(own[name_at_1], bright[name_at_1])
    assert all(bright[n].mean() > dark[n].mean() + 5 for n in own)

    # export: the static model of one exposure; its DC is the model's offset by EV · STEP (moment
    # matching alone, --refine 0: the same Gaussians but for their colour)
    code, out, err = cli("export", run, "-f", "ply-3dgs", "-o", tmp_path / "one.ply", "--at", "exposure=1", "--refine", "0")
    assert code == 0 and "exposure 1" in out, err
    assert cli("export", run, "-f", "ply-3dgs", "-o", tmp_path / "zero.ply", "--at", "exposure=0", "--refine", "0")[0] == 0
    one, zero = read_gaussian_ply(tmp_path / "one.ply"), read_gaussian_ply(tmp_path / "zero.ply")
    torch.testing.assert_close(one.sh[:, 0] - zero.sh[:, 0], torch.full_like(zero.sh[:, 0], STEP / C0),
                               rtol=0, atol=1e-5)
    code, _, err = cli("export", run, "-f", "ply-3dgs", "-o", tmp_path / "none.ply")
    assert code == 1 and "holds one exposure: give an exposure (--at exposure=EV)" in err and err.count("\n") == 1


def test_a_condition_defined_here_refuses_what_it_cannot_use(cli, exposure, exposed, tmp_path):
    # a frame without an exposure when the others have one: one line naming both frames
    broken = tmp_path / "broken"
    broken.mkdir()
    for item in exposed.iterdir():
        (broken / item.name).symlink_to(item)
    (broken / "transforms_test.json").unlink()
    meta = json.loads((exposed / "transforms_test.json").read_text())
    del meta["frames"][1]["exposure"]
    (broken / "transforms_test.json").write_text(json.dumps(meta))
    code, _, err = cli("reconstruct", broken, "-o", tmp_path / "run", "-q")
    assert code == 1 and "has no 'exposure' but frames[0]" in err and "give every frame a 'exposure' or none" in err
    assert not (tmp_path / "run").exists()
    # a value the condition refuses, and a name nobody registered
    assert "'exposure' must be a number in [-4, 4]" in cli("render", broken, "-o", tmp_path / "r", "--at", "exposure=9")[2]
    assert "unknown view condition 'iso' (known: time, light, exposure)" in cli(
        "render", exposed, "-o", tmp_path / "r", "--at", "iso=100")[2]


@pytest.mark.parametrize("name, value", [("time", 0.25), ("light", Light(position=(0.0, 0.0, 3.0), intensity=9.0))])
def test_the_built_in_conditions_pass_the_generic_checks(name, value):
    """What every condition promises the rest of radfield: its scene.json entry and its transforms
    frame keys read back to the value, a camera carries it by name, and its words fill the messages."""
    condition = conditions.get(name)
    assert condition.from_json(json.loads(json.dumps(condition.to_json(value)))) == value
    assert condition.read_frame(json.loads(json.dumps(condition.to_frame(value))), "frame") == value
    assert conditions.view_values({name: condition.to_json(value)}) == {name: value}
    camera = Camera(20.0, 20.0, 8.0, 8.0, 16, 16, look_at((0.0, -3.0, 0.0), (0.0, 0.0, 0.0))).at(**{name: value})
    assert camera.conditions == {name: value} and camera.at(**{name: None}).conditions == {}
    assert condition.key(value) == condition.key(condition.from_row(condition.row(value)))
    assert all(getattr(condition, words) for words in ("plural", "unit", "model_words", "kind_words", "value_words",
                                                       "how", "tag", "once", "how_once"))
    # the kinds that read it: each conditioned kind fixes it for every view (the static model of one value)
    readers = [kind for kind in kinds.registered() if name in kind.conditions]
    assert readers and all(kind.at_conditions is not kinds.PrimitiveKind.at_conditions for kind in readers)


def test_an_option_of_a_condition_is_refused_for_a_model_that_does_not_read_it():
    from radfield.core.kinds import random_neural

    model = random_neural(4)
    for name, option, words in (("time", "--time", "is static and shows one moment"), ("light", "--light", "is not")):
        with pytest.raises(RadfieldError, match=f"{option} is for a .* model; this one \\(neural\\) {words}"):
            conditions.check_takes(model, "m.safetensors", name, option)
    asked = conditions.get("time").asked({"time": 0.5, "times": None})
    assert asked == Asked("--time", value=0.5)
    with pytest.raises(RadfieldError, match="--time and --times exclude each other"):
        conditions.get("time").asked({"time": 0.5, "times": "0:1:3"})


# --- the checks the dynamic and the relighting tests share, once for each built-in condition -------------


@dataclass(frozen=True)
class Case:
    """What differs between the built-in conditions in the shared checks below."""

    data: str                        # the fixture of a tiny dataset whose views carry it
    kinds: tuple[str, str]           # the kinds that read it: the neural one, the Gaussian one
    value: Any                       # a value of it
    model: Callable                  # static primitives -> a model of the kind that reads it (random tensors)
    distinct: int                    # the distinct values of the dataset's train views
    normalised_kept: bool            # whether the training frame's normalisation keeps a value as it is
    one: tuple[str, ...]             # the options that give one value (render, export, view)
    several: tuple[str, ...]         # render's options that give several along a 4-frame path
    drawn_how: str                   # what a kind's error says gives one (core/kinds: view_time, view_light)
    exported: str                    # how a kind's error says a static export holds one
    bad_settings: tuple = ()         # (--set, message): its other settings, mistaken
    render_mistakes: tuple = ()      # (model, args, message): render's options of it, mistaken
    export_mistakes: tuple = ()      # (model, args, message): export's
    view_mistakes: tuple = ()        # (args, message): view's


CASES = {
    "time": Case(
        data="smoke", kinds=("neural-dynamic", "gaussian-dynamic"), value=0.5, model=with_time, distinct=3,
        normalised_kept=True, one=("--time", "0.5"), several=("--times", "0:1:4"), drawn_how="--time T",
        exported="exported at one moment",
        bad_settings=(("render.time_frequency=0", "render.time_frequency must be in (0, 100]"),),
        render_mistakes=(
            ("reader", ["--time", "1.5"], "--time must be a moment in [0, 1]"),
            ("reader", ["--time", "nan"], "--time must be a moment in [0, 1]"),
            ("reader", ["--times", "0:1"], "--times takes START:STOP:COUNT"),
            ("reader", ["--times", "a:b:3"], "--times takes START:STOP:COUNT"),
            ("reader", ["--times", "0:1:0"], "COUNT must be at least 1"),
            ("reader", ["--times", "0:1.5:3"], "STOP must be a moment in [0, 1]"),
            ("reader", ["--times", "-1:1:3"], "START must be a moment in [0, 1]"),
            ("reader", ["--time", "0.5", "--times", "0:1:3"], "--time and --times exclude each other"),
            ("reader", ["--camera", "nope"], "--camera 'nope': no view of that name"),
        ),
        export_mistakes=(("reader", ["-f", "ply-3dgs", "--time", "-0.1"], "--time must be a moment in [0, 1]"),),
        view_mistakes=((["--time", "3"], "--time must be a moment in [0, 1]"),),
    ),
    "light": Case(
        data="olat", kinds=("neural-relight", "gaussian-relight"), value=Light(position=(1.0, -2.5, 1.5), intensity=9.0),
        model=with_network, distinct=6, normalised_kept=False, one=("--light", "3,0,0"), several=("--light-orbit", "4"),
        drawn_how=conditions.get("light").how_once, exported="exported under one light",
        render_mistakes=(
            ("reader", ["--light", "1,2"], "--light takes three finite numbers X,Y,Z"),
            ("reader", ["--light", "1,2,nan"], "--light takes three finite numbers X,Y,Z"),
            ("reader", ["--light-dir", "0,0,0"], "--light-dir must not be 0,0,0"),
            ("reader", ["--light", "3,0,0", "--light-dir", "1,0,0"],
             "--light (a point light) and --light-dir (a directional light) exclude each other"),
            ("reader", ["--light", "3,0,0", "--light-intensity", "0"], "--light-intensity must be a positive number"),
            ("reader", ["--light-intensity", "2"], "--light-intensity is the intensity of --light, --light-dir or --light-orbit"),
            ("reader", ["--light", "3,0,0", "--light-orbit", "3"], "--light and --light-orbit exclude each other"),
            ("reader", ["--light-orbit", "-1"], "--light-orbit must be at least 0, got -1"),
            ("reader", ["--light", "0,0,0.1"], "--light 0,0,0.1 is inside the object's bounds (the box"),
        ),
        export_mistakes=(
            ("reader", ["-f", "ply-3dgs", "--light", "1,x,2"], "--light takes three finite numbers"),
            ("reader", ["-f", "ply-3dgs", "--light-intensity", "3"], "--light-intensity is the intensity of --light or --light-dir"),
        ),
        view_mistakes=(
            (["--light", "1,2"], "--light takes three finite numbers"),
            (["--light", "1,2,3", "--light-dir", "1,0,0"], "exclude each other"),
            (["--light-intensity", "2"], "--light-intensity is the intensity of --light or --light-dir"),
        ),
    ),
}
NAMES = list(CASES)
STATIC_VIEW_KEYS = {"name", "image", "fx", "fy", "cx", "cy", "width", "height", "c2w", "file_width", "file_height",
                    "distortion"}


def test_the_cases_are_the_built_in_conditions():
    assert NAMES == list(conditions.names()) == ["time", "light"]
    for name, case in CASES.items():
        assert list(case.kinds) == [k.name for k in kinds.registered() if k.conditions == (name,)]


@pytest.fixture(scope="module")
def smoke(tmp_path_factory) -> Path:
    """The smoke scene at 16 px: 2 train + 2 test cameras (an orbit about them), each at 3 times."""
    return generate_dynamic("smoke", tmp_path_factory.mktemp("smoke") / "smoke", n_train=2, n_test=2, times=3, size=16)


@pytest.fixture(scope="module")
def olat(tmp_path_factory) -> Path:
    """The olat scene at 16 px: 2 train + 2 test cameras (an orbit about them), each under 3 lights;
    its mesh.ply gives the object's bounds (a box)."""
    return generate_olat(tmp_path_factory.mktemp("olat") / "olat", n_train=2, n_test=2, lights=3, size=16)


@pytest.fixture(scope="module")
def blobs(tmp_path_factory) -> Path:
    """A static dataset: no view carries any condition."""
    return generate_scene("blobs", tmp_path_factory.mktemp("blobs") / "blobs", n_train=3, n_test=1, size=16, mesh=False)


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, Path]:
    """Model files: for each condition one of its neural kind ("time", "light"), and a static one."""
    root = tmp_path_factory.mktemp("models")
    files = {"static": root / "static.safetensors"}
    save_model(files["static"], random_neural(20, extent=0.5, seed=4))
    for name, case in CASES.items():
        files[name] = root / f"{name}.safetensors"
        save_model(files[name], case.model(random_neural(40, scale=0.35, extent=0.6, b2=1.5, w2_amplitude=0.4, seed=0)))
    return files


@pytest.fixture(scope="module")
def static_run(blobs, tmp_path_factory, run_radfield) -> tuple[Path, str]:
    """A run of the static dataset (5 steps: only its files matter) and what reconstruct printed."""
    run = tmp_path_factory.mktemp("static") / "run"
    with contextlib.redirect_stdout(io.StringIO()) as out:
        assert run_radfield("reconstruct", blobs, "-o", run, "--no-cage", "--iterations", "5", "-q") == 0
    return run, out.getvalue()


def dataset(request, name: str) -> Path:
    return request.getfixturevalue(CASES[name].data)


def drop(condition, frame: dict) -> None:
    """Remove the keys that give the frame its value of `condition`."""
    for key in condition.to_frame(condition.read_frame(frame, "frame")):
        frame.pop(key)


# --- reading: transforms.json frames, scene.json ---------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_a_static_dataset_has_none(name, blobs):
    cameras = load_dataset(blobs, "all").cameras
    assert cameras and all(name not in cam.conditions for cam in cameras)


@pytest.mark.parametrize("name", NAMES)
def test_nerfstudio_frames_carry_their_value(name, request, tmp_path):
    condition = conditions.get(name)
    root = nerfstudio_copy(dataset(request, name), tmp_path / "ns")
    loaded = load_dataset(root, "all")
    assert loaded.format == "nerfstudio"
    expected = {Path(f["file_path"]).stem: condition.read_frame(f, "frame") for f in frames(root / "transforms.json")}
    assert None not in expected.values() and len(set(map(condition.key, expected.values()))) == CASES[name].distinct
    assert {cam.name: cam.conditions.get(name) for cam in loaded.cameras} == expected


# (file to edit, which frames lose their value, the frame named, what the message says)
MISSING = {
    "some frames of a file": ("transforms_train.json", lambda fs: fs[4:5], 4, "has {no} but frames[0] has one: {hint}"),
    "the first frame only": ("transforms_train.json", lambda fs: fs[1:], 1, "has {no} but frames[0] has one: {hint}"),
    "all but the first frame": ("transforms_train.json", lambda fs: fs[:1], 1, "has {a} but frames[0] has none: {hint}"),
    "one split file": ("transforms_test.json", lambda fs: fs, 0,
                       "has {no} but frames[0] of {root}/transforms_train.json has one: {hint}"),
}


@pytest.mark.parametrize("case", MISSING)
@pytest.mark.parametrize("name", NAMES)
def test_frames_with_and_without_a_value_are_one_line_naming_file_and_frame(name, case, request, tmp_path, cli):
    condition = conditions.get(name)
    file, which, index, message = MISSING[case]
    root = tmp_path / "bad"
    shutil.copytree(dataset(request, name), root)
    rewrite(root / file, lambda fs: [drop(condition, f) for f in which(fs)])
    file_path = frames(root / file)[index]["file_path"]
    code, _, err = cli("reconstruct", root, "-o", tmp_path / "run")
    assert code == 1 and err.count("\n") == 1, err
    assert err.startswith(f"radfield: error: {root / file}: frames[{index}] ({file_path})"), err
    a, no = condition.frame_words
    assert message.format(a=a, no=no, hint=condition.frame_hint, root=root) in err, err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("name", NAMES)
def test_nerfstudio_with_only_some_values_is_one_line(name, request, tmp_path, cli):
    condition = conditions.get(name)
    root = nerfstudio_copy(dataset(request, name), tmp_path / "ns")
    rewrite(root / "transforms.json", lambda fs: drop(condition, fs[3]))
    file_path = frames(root / "transforms.json")[3]["file_path"]
    code, _, err = cli("reconstruct", root, "-o", tmp_path / "run")
    assert code == 1 and err.count("\n") == 1, err
    assert (f"{root / 'transforms.json'}: frames[3] ({file_path}) has {condition.frame_words[1]} but frames[0] has "
            f"one: {condition.frame_hint}") in err, err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("name", NAMES)
def test_scene_json_round_trip_keeps_the_values(name, request, tmp_path):
    condition, data = conditions.get(name), dataset(request, name)
    expected = {split: [condition.read_frame(f, "frame") for f in frames(data / f"transforms_{split}.json")]
                for split in ("train", "test")}
    assert None not in expected["train"] + expected["test"]
    assert len(set(map(condition.key, expected["train"]))) == CASES[name].distinct
    scene_json, _ = read_dataset(data, load_defaults()["data"])
    for split, values in expected.items():
        assert [view[name] for view in scene_json["splits"][split]] == [condition.to_json(v) for v in values]
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene_json))
    scene = load_scene(path)
    assert name in conditions.view_conditions(scene.splits)
    everything = sorted({condition.key(v) for v in expected["train"] + expected["test"]})
    assert [condition.key(condition.from_json(v)) for v in conditions.distinct(scene.splits, name)] == everything
    for split, values in expected.items():
        assert scene.values(name, split) == values
        assert [cam.conditions.get(name) for cam in scene.cameras(split)] == values
        assert [cam.conditions.get(name) for cam in scene.dataset(split).cameras] == values
    camera = scene.cameras("train")[1]
    normalised = scene.normalization.camera(camera)
    assert normalised.conditions[name] == condition.normalized(camera.conditions[name], scene.normalization)
    assert (normalised.conditions[name] == camera.conditions[name]) is CASES[name].normalised_kept
    assert normalised.c2w[:3, 3].norm() <= 1.0 + 1e-9


@pytest.mark.parametrize("name", NAMES)
def test_a_static_scene_json_has_no_key_of_it(name, blobs):
    scene_json, _ = read_dataset(blobs, load_defaults()["data"])
    assert all(set(view) == STATIC_VIEW_KEYS for views in scene_json["splits"].values() for view in views)
    scene = scene_from_json(scene_json, blobs / "scene.json")
    assert name not in conditions.view_conditions(scene.splits) and conditions.distinct(scene.splits, name) == []
    assert set(scene.values(name, "train")) == {None}
    assert all(name not in cam.conditions for cam in scene.cameras("train"))


# --- the kinds: a view without a value, and the kinds that ignore one -----------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_a_view_without_a_value_is_one_error_and_the_other_kinds_ignore_it(name, render_scene):
    condition, case = conditions.get(name), CASES[name]
    for kind, base in zip(case.kinds, ("neural-window", "gaussian")):
        static, cam = render_scene(base, torch.float64)
        prims = case.model(static)
        assert kinds.of(prims).name == kind
        with pytest.raises(RadfieldError, match=rf"^this model is {condition.model_words}: give "
                                                rf"{condition.value_words} \({re.escape(case.drawn_how)}\)$"):
            render(prims, cam)
        with pytest.raises(RadfieldError, match=rf"^a {condition.model_words} model \({kind}\) is {case.exported}: "
                                                rf"give {condition.value_words} \({re.escape(case.drawn_how)}\)$"):
            kinds.of(prims).to_gaussians(prims)
    # every kind that does not read it draws a view with it as the same view without it: the static
    # kind, and those of the other conditions (each at its own value)
    static, cam = render_scene("neural", torch.float64)
    assert kinds.of(static).at_view(static, cam.at(**{name: case.value})) is static
    for model in [static] + [CASES[other].model(static) for other in NAMES if other != name]:
        own = cam.at(**{other: CASES[other].value for other in kinds.of(model).conditions})
        torch.testing.assert_close(render(model, own.at(**{name: case.value})).color, render(model, own).color,
                                   rtol=0, atol=0)


# --- the pipeline: the kinds that read it, the settings, the runs without it ----------------------------


@pytest.mark.parametrize("name", NAMES)
def test_a_static_run_has_no_figures_per_value(name, static_run, cli):
    run, out = static_run
    condition = conditions.get(name)
    assert f"{condition.model_words} scene" not in out, out
    m = json.loads((run / "eval" / "metrics.json").read_text())
    assert m["kind"] == "neural" and f"per_{name}" not in m and all(name not in v for v in m["per_view"])
    report = (run / "eval" / "report.md").read_text()
    assert f"Per {name}" not in report and "Over time" not in report
    assert not any((run / "eval" / "figures").iterdir())
    code, text, _ = cli("info", run, "--json")
    stages = json.loads(text)["stages"]
    assert code == 0 and "kind" not in stages["init"] and condition.plural not in stages["data"]


@pytest.mark.parametrize("name, kind", [(name, kind) for name in NAMES for kind in CASES[name].kinds])
def test_a_kind_that_reads_it_on_views_without_it_is_one_error_line(name, kind, blobs, tmp_path, cli):
    code, _, err = cli("reconstruct", blobs, "-o", tmp_path / "run", "--set", f"train.primitive={kind}", "-q")
    assert code == 1 and err.count("\n") == 1 and not (tmp_path / "run").exists()
    words = conditions.get(name).kind_words
    assert f"{blobs}" in err and f"train.primitive is {kind}, a {words} kind, but the dataset's views carry no {name}" in err


@pytest.mark.parametrize("name", NAMES)
def test_a_kind_that_reads_it_with_it_ignored_is_one_error_line(name, request, tmp_path, cli):
    kind = CASES[name].kinds[0]
    code, _, err = cli("reconstruct", dataset(request, name), "-o", tmp_path / "run", "--set", f"train.primitive={kind}",
                       "--set", f"data.{name}=ignore", "-q")
    assert code == 1 and err.count("\n") == 1 and not (tmp_path / "run").exists(), err
    assert f"train.primitive is {kind}, a {conditions.get(name).kind_words} kind, but data.{name} is ignore" in err, err


@pytest.mark.parametrize("name, setting, words", [(name, f"data.{name}=never", "must be one of auto, ignore")
                                                  for name in NAMES]
                         + [(name, *bad) for name in NAMES for bad in CASES[name].bad_settings])
def test_bad_settings_of_it_are_one_error_line(name, setting, words, request, tmp_path, cli):
    code, _, err = cli("reconstruct", dataset(request, name), "-o", tmp_path / "run", "--set", setting, "-q")
    assert code == 1 and err.count("\n") == 1 and words in err and not (tmp_path / "run").exists(), err


@pytest.mark.parametrize("name", NAMES)
def test_a_model_that_reads_it_is_not_measured_on_views_without_it(name, request, models, blobs, tmp_path, cli):
    # a run (made by hand: what it holds is not what is checked) of a model of the kind that reads it
    run = tmp_path / "run"
    (run / "train").mkdir(parents=True)
    shutil.copy(models[name], run / "train" / "model.safetensors")
    (run / "radfield-run.json").write_text(json.dumps({"kind": "radfield-run", "input": str(dataset(request, name))}))
    (run / "config.yaml").write_text("data:\n  background: [1, 1, 1]\n")
    kind = CASES[name].kinds[0]
    for verb in ("eval", "bake"):
        out = tmp_path / (verb + (".safetensors" if verb == "bake" else ""))
        code, _, err = cli(verb, run, "--dataset", blobs, "-o", out, "-q")
        assert code == 1 and err.count("\n") == 1 and not out.exists(), (verb, err)
        assert (f"a {conditions.get(name).kind_words} model ({kind}) is measured on views that carry a {name}, "
                f"but the views of {blobs} carry no {name}") in err, (verb, err)


# --- delivery: render's, export's and view's options of it, mistaken -------------------------------------


def refused(name: str, option: str, kind: str) -> str:
    """The message of `option` of condition `name` given for a model of `kind`, which does not read it."""
    condition = conditions.get(name)
    return f"{option} is for a {condition.model_words} model; this one ({kind}) {condition.without}"


def render_mistakes():
    for name, case in CASES.items():
        condition, kind = conditions.get(name), case.kinds[0]
        yield name, "reader", ["--orbit", "3"], (f"this model is {condition.model_words} ({kind}): give "
                                                 f"{condition.value_words} for the orbit ({condition.how})")
        yield name, "reader", ["--orbit", "3", *case.several], (f"{case.several[0]} gives 4 {condition.unit} but the "
                                                                "orbit has 3 frames")
        yield name, "static", list(case.one), refused(name, case.one[0], "neural")
        yield name, "static", list(case.several), refused(name, case.several[0], "neural")
        for other in NAMES:   # another condition's value for this model
            if other != name:
                yield name, "reader", list(CASES[other].one), refused(other, CASES[other].one[0], kind)
        yield from ((name, *mistake) for mistake in case.render_mistakes)


@pytest.mark.parametrize("name, model, args, message", list(render_mistakes()))
def test_render_options_of_it_mistaken_are_one_line(name, model, args, message, request, models, tmp_path, cli):
    code, _, err = cli("render", models[name if model == "reader" else "static"], "-d", dataset(request, name),
                       "-o", tmp_path / "out", "--video", tmp_path / "v.mp4", *args)
    assert code == 1 and message in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists() and not (tmp_path / "v.mp4").exists()


def export_mistakes():
    for name, case in CASES.items():
        condition, kind = conditions.get(name), case.kinds[0]
        holds = f"holds {condition.once}: give {condition.value_words} ({condition.how_once})"
        yield name, "reader", ["-f", "ply-3dgs"], f"the model is {condition.model_words} ({kind}) and ply-3dgs {holds}"
        yield name, "reader", ["-f", "splat"], f"the model is {condition.model_words} ({kind}) and splat {holds}"
        yield name, "static", ["-f", "ply-3dgs", *case.one], refused(name, case.one[0], "neural")
        yield from ((name, *mistake) for mistake in case.export_mistakes)


@pytest.mark.parametrize("name, model, args, message", list(export_mistakes()))
def test_export_options_of_it_mistaken_are_one_line(name, model, args, message, models, tmp_path, cli):
    out = tmp_path / ("out.splat" if "splat" in args else "out.ply")
    code, _, err = cli("export", models[name if model == "reader" else "static"], "-o", out, *args)
    assert code == 1 and message in err and err.count("\n") == 1, err
    assert not out.exists()


def view_mistakes():
    for name, case in CASES.items():
        yield name, "static", list(case.one), refused(name, case.one[0], "neural")
        yield from ((name, "reader", *mistake) for mistake in case.view_mistakes)


@pytest.mark.parametrize("name, model, args, message", list(view_mistakes()))
def test_view_options_of_it_mistaken_are_one_line(name, model, args, message, models, cli):
    code, _, err = cli("view", models[name if model == "reader" else "static"], "--port", "0", *args)
    assert code == 1 and message in err and err.count("\n") == 1, err
