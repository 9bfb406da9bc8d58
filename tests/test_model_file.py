"""The model file format: round trip, and a precise one-line error for every way it can be wrong."""

import json
from dataclasses import replace

import pytest
import torch
from safetensors.torch import save_file

from radfield.errors import RadfieldError
from radfield.model_file import load_model, read_metadata, save_model
from radfield.core.kinds import NeuralPrimitives, random_gaussians, random_neural


@pytest.mark.parametrize("make", [lambda: random_neural(7, sh_degree=2, omega0=20.0),
                                  lambda: replace(random_neural(7, sh_degree=2, omega0=20.0), window=True),
                                  lambda: random_gaussians(5, sh_degree=3)])
def test_round_trip(tmp_path, make):
    prims = make()
    save_model(tmp_path / "m.safetensors", prims, extra={"normalization": {"scale": 2.0}})
    back = load_model(tmp_path / "m.safetensors")
    assert type(back) is type(prims) and back.sh_degree == prims.sh_degree
    for k, v in prims.tensors().items():
        torch.testing.assert_close(getattr(back, k), v)
    meta = read_metadata(tmp_path / "m.safetensors")
    assert meta["format"] == "radfield" and meta["version"] == "1" and meta["kind"] == prims.kind
    assert json.loads(meta["normalization"]) == {"scale": 2.0}
    if isinstance(prims, NeuralPrimitives):
        assert back.omega0 == 20.0 and back.window == prims.window
        assert meta.get("window") == ("1" if prims.window else None)   # a hard-edged model's file is unchanged
    assert not list(tmp_path.glob("*.tmp"))


def _write(path, tensors, **meta):
    base = {"format": "radfield", "kind": "neural", "version": "1", "omega0": "30.0", "sh_degree": "1"}
    base.update(meta)
    save_file(tensors, str(path), metadata={k: v for k, v in base.items() if v is not None})


def _neural_tensors(p=4, n=8, k=4):
    prims = random_neural(p, hidden=n, sh_degree={1: 0, 4: 1, 9: 2, 16: 3}[k])
    return {k: v.contiguous() for k, v in prims.tensors().items()}


@pytest.mark.parametrize("change, message", [
    (lambda t, m: m.update(format="other"), "metadata format is 'other'"),
    (lambda t, m: m.update(version="7"), "format version '7' is not supported"),
    (lambda t, m: m.update(kind="splat"), "metadata kind is 'splat'"),
    (lambda t, m: m.update(omega0="abc"), "metadata 'omega0' is missing or not a number"),
    (lambda t, m: m.update(omega0=None), "metadata 'omega0' is missing"),
    (lambda t, m: m.update(sh_degree="5"), "sh_degree=5 is outside 0..3"),
    (lambda t, m: m.update(window="yes"), "metadata window='yes' is not 0 or 1"),
    (lambda t, m: m.update(sh_degree="2"), "tensor 'sh' has shape (4, 4, 3), expected (P, 9, 3) with P=4, K=9 for sh_degree=2"),
    (lambda t, m: t.pop("w2"), "missing tensors ['w2'] for kind=neural"),
    (lambda t, m: t.update(extra=torch.zeros(4)), "unexpected tensors ['extra']"),
    (lambda t, m: t.update(b1=torch.zeros(4, 5)), "tensor 'b1' has shape (4, 5), expected (P, 8) with P=4"),
    (lambda t, m: t.update(means=torch.zeros(3, 3)), "tensor 'means' has shape (3, 3), expected (P, 3) with P=4"),
    (lambda t, m: t.update(b2=torch.zeros(4, dtype=torch.float64)), "tensor 'b2' has dtype float64, expected float32"),
    (lambda t, m: t["w1"].__setitem__((2, 0, 0), float("nan")), "tensor 'w1' holds 1 NaN/Inf values (first at primitive 2)"),
    (lambda t, m: t["quats"].__setitem__(1, 0.0), "tensor 'quats' has all-zero rows"),
    (lambda t, m: m.update(sh_degree="-1"), "sh_degree=-1 is outside 0..3"),
    # values out of range (the kinds' check_values): these loaded and rendered as background
    (lambda t, m: t["log_scales"].__setitem__((1, 2), 100.0),
     "tensor 'log_scales' is out of range at primitive 1 (a log scale of 100 is outside [-25, 25]"),
    (lambda t, m: t["log_scales"].__setitem__((3, 0), -40.0),
     "tensor 'log_scales' is out of range at primitive 3 (a log scale of -40 is outside [-25, 25]"),
    (lambda t, m: t["means"].__setitem__((2, 1), 1e20), "tensor 'means' is out of range at primitive 2"),
    (lambda t, m: t["quats"].__setitem__(0, 1e-30), "tensor 'quats' is out of range at primitive 0"),
    (lambda t, m: t.update(rest_metric=torch.tensor([[1.0, 1, 1, 0, 0, 0]] * 2 + [[0.0] * 6] * 2)),
     "tensor 'rest_metric' is out of range at primitive 2 (not positive definite"),
    (lambda t, m: t["w1"].__setitem__((1, 0, 0), 1e30), "tensor 'w1' is out of range at primitive 1"),
])
def test_bad_files_are_rejected_precisely(tmp_path, change, message):
    tensors, meta = _neural_tensors(), {}
    change(tensors, meta)
    path = tmp_path / "bad.safetensors"
    _write(path, tensors, **meta)
    with pytest.raises(RadfieldError) as err:
        load_model(path)
    assert message in str(err.value) and str(path) in str(err.value)
    assert "\n" not in str(err.value)


def test_not_a_safetensors_file(tmp_path):
    for name, payload in [("garbage.safetensors", b"\x00\x01garbage" * 10), ("empty.safetensors", b"")]:
        path = tmp_path / name
        path.write_bytes(payload)
        with pytest.raises(RadfieldError, match="not a readable safetensors file"):
            load_model(path)
    # a pickle (what torch.save writes) is refused, never unpickled
    torch.save({"means": torch.zeros(2, 3)}, tmp_path / "model.pt")
    with pytest.raises(RadfieldError, match="not a readable safetensors file"):
        load_model(tmp_path / "model.pt")
    with pytest.raises(RadfieldError, match="no such model file"):
        load_model(tmp_path / "missing.safetensors")


def test_gaussian_values_are_checked(tmp_path):
    tensors = {k: v.contiguous() for k, v in random_gaussians(3).tensors().items()}
    tensors["log_scales"][2, 1] = 60.0
    _write(tmp_path / "g.safetensors", tensors, kind="gaussian", omega0=None, sh_degree="0")
    with pytest.raises(RadfieldError, match=r"tensor 'log_scales' is out of range at primitive 2"):
        load_model(tmp_path / "g.safetensors")


def test_the_value_ranges_hold_for_trained_and_edited_models(tmp_path):
    """The bounds are far from what training writes: a model saved with the extremes a trained model
    of a scene in metres ... kilometres or millimetres could have still loads."""
    prims = random_neural(6, sh_degree=1)
    prims.log_scales[0] = torch.tensor([-20.0, 0.0, 20.0])   # 2 nm .. 485 000 km
    prims.means[1] = torch.tensor([1e9, -1e9, 0.0])
    save_model(tmp_path / "m.safetensors", prims)
    torch.testing.assert_close(load_model(tmp_path / "m.safetensors").log_scales, prims.log_scales)


def test_gaussian_schema(tmp_path):
    prims = random_gaussians(3)
    tensors = {k: v.contiguous() for k, v in prims.tensors().items()}
    tensors.pop("opacities")
    _write(tmp_path / "g.safetensors", tensors, kind="gaussian", omega0=None, sh_degree="0")
    with pytest.raises(RadfieldError, match=r"missing tensors \['opacities'\] for kind=gaussian"):
        load_model(tmp_path / "g.safetensors")


def test_equal_models_give_equal_bytes(tmp_path):
    """The stage cache hashes file contents: saving the same model twice must give the same bytes
    (safetensors alone writes its metadata in hash-map order)."""
    prims = random_neural(4, sh_degree=1)
    blobs = set()
    for i in range(4):
        save_model(tmp_path / f"m{i}.safetensors", prims, extra={"a": "1", "b": "2", "c": "3"})
        blobs.add((tmp_path / f"m{i}.safetensors").read_bytes())
    assert len(blobs) == 1
