"""The typed configuration (radfield/pipeline/schema.py): it agrees with pipeline.yaml, every key is
documented, the stages' cache keys read off it are those of the plain config (and of the runs made
before it existed), and docs/configuration.md is what the generator writes."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from radfield.pipeline import config as pipeline_config
from radfield.pipeline import schema
from radfield.pipeline.config import load_config, load_defaults, section
from radfield.pipeline.runner import INPUT, Stage, read_manifest, run_pipeline
from radfield.pipeline.schema import Config, typed

ROOT = Path(__file__).resolve().parents[1]

# The cache key (sha256 of the hashed section) of each stage's config_keys under the defaults, as
# computed before the schema existed: a run made then must stay cached. Update a digest only when
# a default of pipeline.yaml changes on purpose (which re-runs that stage in every run directory).
# data.max_size is not hashed (it acts through data.downscale, which stages/data.resolve fills in
# first: 1 for a dataset within the limit, as every run made before data.max_size existed).
DATA = tuple(f"data.{key}" for key in ("downscale", "background", "test_every", "val_every", "time", "light"))
PINNED = {
    ("sfm", "seed"): "aac22a3cf799fd45a097908b3e518f48c9e44758142a600a6a57ece44c5adf12",   # sfm, triangulate
    DATA: "2a94fbdcbd5addc5cf3fcc633b105f4cf407e068cb3417dc4313df85de2cb62f",
    # envelope: ("envelope", "sfm", "seed") until the triangulate stage took over its triangulation
    ("envelope",): "8126f92e78aaa0a352565306cc2634c8d9bf00891ee998223cf77414621f35c7",
    ("tetra",): "71b16c0932348c70d95a1190095f01668a48dbf9cb7e1a3c1f70a483029e0bd7",
    # init: + footprint_px, then footprint_cone with footprint_px 12 by default (issue 40; an existing
    # run re-runs init once, which writes the same model unless its views are forward-facing, so that
    # training stays cached)
    ("init", "train.primitive", "train.sh_degree", "train.max_primitives", "render.omega0", "render.hidden",
     "render.window", "render.time_frequency", "seed"): "3a3ddfdeb83a855a84a67d7fda5a4df9950052cafa44cc4640737ec1f65d2d3d",
    # train: + coarse_levels and coarse_until (issue 40; an existing run retrains once)
    ("train", "render", *DATA, "seed"): "292fba2e848bae94cb391b04797a71d9641bf5b6329b84d9a0cb5edf29bcbb1c",
    ("bake", "eval.split", "render.near"): "3d9fc7d2f27f12fa81031e0f1540dfeed401142961cdf9a24fc82c803712cd2c",
    ("eval", "render.near", "render.supersample"): "84be6d003c8677221a2900acda18c506cfc8ac0052a7b463fa5114927f1fb0e7",
}


def _digest(value) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()   # runner._digest


def test_the_defaults_are_a_typed_config() -> None:
    defaults = load_defaults()
    config = typed(defaults)
    assert config.train.lr.means == 1.6e-4 and config.train.max_primitives is None
    assert config.data.background == (1.0, 1.0, 1.0) and config.stages[0] == "sfm"
    assert json.dumps(schema.plain(config)) == json.dumps(defaults)   # same keys, same order, same values
    assert list(schema.names()) == list(pipeline_config._names(defaults))


def test_every_key_and_section_is_documented() -> None:
    for name, key in schema.keys().items():
        parent, _, leaf = name.rpartition(".")
        cls = schema.find(parent) if parent else Config
        assert cls.__doc__ and cls.__doc__.strip(), parent
        assert schema.docs(cls).get(leaf, "").strip(), f"{name} has no docstring"


@pytest.mark.parametrize(("change", "message"), [
    (lambda d: d["train"].update(extra=1), "only in pipeline.yaml: \\['train.extra'\\]"),
    (lambda d: d["render"].pop("near"), "only in the schema: \\['render.near'\\]"),
    (lambda d: d["train"].update(iterations=3000.0), "train.iterations must be an integer"),
    (lambda d: d["render"].update(near=1), "render.near must be a number"),
    (lambda d: d["train"].update(sh_degree=7), "train.sh_degree must be in \\[0, 3\\]"),
])
def test_a_pipeline_yaml_that_disagrees_with_the_schema_is_a_bug(change, message) -> None:
    defaults = load_defaults()
    change(defaults)
    with pytest.raises(ValueError, match=message):
        pipeline_config._check_defaults(defaults)


def test_cache_keys_are_those_of_the_runs_made_before_the_schema() -> None:
    # the automatic data.downscale (null) as stages/data.resolve records it for images within data.max_size
    from radfield.stages.data import DATA_KEYS

    assert DATA_KEYS == DATA
    defaults = load_config(sets=["data.downscale=1"])
    for keys, digest in PINNED.items():
        assert _digest(section(defaults, keys)) == digest, keys
        assert _digest(section(typed(defaults), keys)) == digest, keys


def test_every_stage_key_is_a_schema_key_and_reads_the_same_typed() -> None:
    from radfield.core import kinds
    from radfield.stages import registry

    declared = [stage.config_keys for stage in registry.stages()] + [kind.init_config_keys for kind in kinds.registered()]
    config = load_config(sets=["train.max_primitives=500", "data.background=[0, 0.5, 1]", "render.near=0.1"])
    for keys in declared:
        assert all(schema.find(key) is not None for key in keys), keys
        # the same dict, in the same order (the manifest records it)
        assert json.dumps(section(typed(config), keys)) == json.dumps(section(config, keys)), keys


def test_a_typed_config_runs_as_its_plain_form(tmp_path: Path) -> None:
    """run_pipeline given the typed config writes the same RUN/config.yaml and cache key as given the
    plain one: the second run is cached."""
    def write(ctx) -> None:
        ctx.outputs["out.txt"].write_text(json.dumps(ctx.config))

    dataset = tmp_path / "dataset"
    dataset.mkdir()
    stage = Stage("data", write, config_keys=("data", "render.near", "seed"), inputs=(INPUT,), outputs=("out.txt",))
    config = load_config(sets=["stages=[data]", "data.downscale=2"])
    assert run_pipeline([stage], tmp_path / "run", typed(config), input_path=dataset, quiet=True) == {"data": "ran"}
    written = (tmp_path / "run" / "config.yaml").read_text()
    assert run_pipeline([stage], tmp_path / "run", config, input_path=dataset, quiet=True) == {"data": "cached"}
    assert (tmp_path / "run" / "config.yaml").read_text() == written
    assert load_config(tmp_path / "run" / "config.yaml") == config
    assert read_manifest(tmp_path / "run" / "data")["config"] == section(config, stage.config_keys)


def test_the_configuration_reference_is_up_to_date() -> None:
    from radfield.pipeline.reference import render

    committed = (ROOT / "docs" / "configuration.md").read_text(encoding="utf-8")
    assert committed == render(), "regenerate it: python -m radfield.pipeline.reference > docs/configuration.md"
