"""The browser renderer (`radfield export -f web`, `radfield view`): model.bin's precision and layout,
the folder, and in a real browser (headless Chromium, software WebGL, driven over DevTools) the
page's frame of a test camera against `radfield render` of the same camera, for every kind."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import safetensors.torch

from radfield.bench.render import bench_models
from radfield.core.geometry.cage import write_binding, write_cage
from radfield.core.geometry.rotations import quat_to_rotmat
from radfield.delivery.web import model_bin
from radfield.delivery.web.browser import chromium_path, headless_chromium
from radfield.delivery.web.serve import serving, web_server
from radfield.edit.field import box_cage
from radfield.model_file import load_model, save_model

SIZE = 96            # the test cameras' side, pixels
PRIMITIVES = 600
STATIC_MIN_PSNR = 40.0       # issue 43's targets: the static kinds, the conditioned ones
CONDITIONED_MIN_PSNR = 35.0


# --- model.bin ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["neural", "gaussian", "neural-dynamic", "gaussian-relight"])
def test_model_bin_round_trip(kind):
    """float32 keeps every number; compact is float16, 16-bit means in the box (error ≤ half a step)
    and smallest-three rotations (the same rotation to float16's precision), under half the bytes."""
    model = bench_models(2000, (kind,))[kind]
    exact = model_bin.decoded(model, model_bin.encode(model, compact=False))
    for name, t in model.tensors().items():
        assert torch.equal(getattr(exact, name), t), name
    blob = model_bin.encode(model, compact=True)
    compact = model_bin.decoded(model, blob)
    span = model.means.amax(0) - model.means.amin(0)
    assert ((compact.means - model.means).abs() <= span / model_bin.U16 / 2 * 1.001 + 1e-7).all()
    rot, rot_compact = quat_to_rotmat(model.quats), quat_to_rotmat(compact.quats)
    assert (rot - rot_compact).abs().max() < 2e-3
    for name, t in model.tensors().items():
        if name not in ("means", "quats"):
            assert torch.allclose(getattr(compact, name), t.half().float()), name
    full = len(model_bin.encode(model, compact=False))
    assert len(blob) < 0.5 * full
    meta, tensors = model_bin.metadata(blob), safetensors.torch.load(blob)
    assert meta["format"] == "radfield-web" and meta["kind"] == kind and meta["sh_degree"] == str(model.sh_degree)
    assert tensors["means"].dtype == torch.uint16 and tensors["quats_index"].dtype == torch.uint8


# --- runs of every kind, made by hand on a generated dataset ----------------------------------------------

@pytest.fixture(scope="module")
def runs(tmp_path_factory, run_radfield) -> dict[str, Path]:
    """{case: run directory}: a 96-px blobs dataset's data stage, then a model of each kind (the
    bench scene's primitives, SH degree 3) dropped in as the trained model, with a box cage and its
    binding; "edited" is the neural run twisted and moved by `radfield edit` (opacity preserved:
    the model carries rest metrics)."""
    from radfield.demo.static import generate_scene

    root = tmp_path_factory.mktemp("web")
    data = generate_scene("blobs", root / "data", n_train=2, n_test=2, size=SIZE, seed=0, mesh=False)
    models = bench_models(PRIMITIVES, ("neural", "gaussian", "neural-dynamic", "neural-relight"), scale=0.09)
    out = {}
    for kind, model in models.items():
        run = root / kind
        assert run_radfield("reconstruct", data, "-o", run, "--until", "data", "--primitive", "neural", "-q") == 0
        (run / "train").mkdir()
        save_model(run / "train" / "model.safetensors", model.map(lambda t: t * 0.6 if t is model.means else t))
        out[kind] = run
    run = out["neural"]
    vertices, tets = box_cage([-1.0] * 3, [1.0] * 3, 2)
    write_cage(run / "tetra", vertices, tets)
    (run / "bind").mkdir()
    write_binding(run / "bind" / "model_binding.npz", load_model(run / "train" / "model.safetensors").means.numpy(),
                  run / "tetra" / "cage.npz")
    spec = root / "edit.yaml"
    spec.write_text("operations:\n- twist: {axis: z, degrees_per_unit: 40, origin: [0, 0, 0], select: all}\n")
    assert run_radfield("edit", run, "--spec", spec, "-o", root / "edited", "--translate", "0.1,0,0", "-q") == 0
    out["edited"] = root / "edited"
    return out


def test_export_web_writes_the_folder(cli, runs, tmp_path):
    run = runs["neural-dynamic"]
    code, stdout, err = cli("export", run, "-f", "web", "-o", tmp_path / "site", "--time", "0.25")
    assert code == 0, err
    assert "precision float16" in stdout and "dB against float32" in stdout
    names = {p.name for p in (tmp_path / "site").iterdir()}
    assert {"index.html", "view.json", "model.bin", "viewer.js", "renderer.js"} <= names
    view = json.loads((tmp_path / "site" / "view.json").read_text())
    assert view["start"] == "test:0" and len(view["cameras"]["test"]) == 2 and len(view["cameras"]["train"]) == 2
    assert view["conditions"] == {"time": {"start": 0.25}} and view["kind"] == "neural-dynamic"
    source = (run / "train" / "model.safetensors").stat().st_size
    assert (tmp_path / "site" / "model.bin").stat().st_size <= 0.5 * source + 1024   # + its longer header
    # the output policy: a non-empty folder needs --force
    code, _, err = cli("export", run, "-f", "web", "-o", tmp_path / "site")
    assert code != 0 and "not empty" in err and err.count("\n") == 1


# --- in the browser --------------------------------------------------------------------------------

def _need_chromium() -> None:
    if chromium_path() is None:
        if os.environ.get("CI") == "true":
            pytest.fail("chromium is missing (apt-get install -y chromium): the browser renderer cannot be tested")
        pytest.skip("chromium is not installed (apt-get install -y chromium)")


@pytest.fixture(scope="module")
def page():
    _need_chromium()
    with headless_chromium() as page:
        yield page


def _page_frame(page, site: Path, hash: str, width: int, height: int) -> np.ndarray:
    with serving(web_server(site, "127.0.0.1", 0)) as url:
        page.open(f"{url}index.html#{hash}", width, height)
        page.wait_ready()
        return page.screenshot()


def _render(cli, run: Path, tmp_path: Path, *options) -> np.ndarray:
    out = tmp_path / f"render{len(list(tmp_path.glob('render*')))}"
    code, _, err = cli("render", run, "-o", out, "--camera", "0", "-q", *options)
    assert code == 0, err
    (png,) = out.glob("*.png")
    return cv2.cvtColor(cv2.imread(str(png)), cv2.COLOR_BGR2RGB)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2) / 255**2
    return float("inf") if mse == 0 else -10 * np.log10(mse)


CASES = [  # (case, run, export options, page hash, render options, bound)
    ("neural", "neural", (), "", (), STATIC_MIN_PSNR),
    ("gaussian", "gaussian", (), "", (), STATIC_MIN_PSNR),
    ("neural-dynamic t=0.2", "neural-dynamic", (), "&time=0.2", ("--time", "0.2"), CONDITIONED_MIN_PSNR),
    ("neural-dynamic t=0.9", "neural-dynamic", ("--time", "0.9"), "", ("--time", "0.9"), CONDITIONED_MIN_PSNR),
    ("neural-relight point", "neural-relight", (), "&light=0,0,3&intensity=9",
     ("--light", "0,0,3", "--light-intensity", "9"), CONDITIONED_MIN_PSNR),
    ("neural-relight directional", "neural-relight", (), "&lightdir=1,-1,-1&intensity=1.5",
     ("--light-dir", "1,-1,-1", "--light-intensity", "1.5"), CONDITIONED_MIN_PSNR),
    ("edited", "edited", (), "", ("-d", None), STATIC_MIN_PSNR),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_the_page_draws_what_render_draws(case, runs, page, cli, tmp_path):
    """The page at the run's first test camera (#view=test:0&ui=0, a viewport of the camera's size)
    against `radfield render` of that camera: PSNR ≥ 40 dB (static kinds) / 35 dB (conditioned)."""
    name, which, export_options, hash, render_options, bound = case
    run = runs[which]
    site = tmp_path / "site"
    code, _, err = cli("export", run, "-f", "web", "-o", site, *export_options)
    assert code == 0, err
    if "-d" in render_options:   # an edited run renders its source run's dataset
        render_options = ("-d", json.loads((runs["neural"] / "radfield-run.json").read_text())["input"])
    ours = _render(cli, run, tmp_path, "--split", "test", *render_options)
    frame = _page_frame(page, site, f"view=test:0&ui=0{hash}", ours.shape[1], ours.shape[0])
    covered = (np.abs(ours.astype(int) - 255).sum(-1) > 30).mean()
    assert covered > 0.05, f"{name}: the test view shows too little of the model ({covered:.0%})"
    assert frame.shape == ours.shape
    value = _psnr(frame, ours)
    print(f"{name}: PSNR {value:.2f} dB, {covered:.0%} of the view covered")
    if os.environ.get("RADFIELD_KEEP_WEB_FRAMES"):
        keep = Path(os.environ["RADFIELD_KEEP_WEB_FRAMES"])
        keep.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(keep / f"{name}-page.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(keep / f"{name}-render.png"), cv2.cvtColor(ours, cv2.COLOR_RGB2BGR))
    assert value >= bound, f"{name}: the page's frame is {value:.2f} dB from radfield render's (bound {bound} dB)"


@pytest.mark.parametrize("damage", ["truncated", "header", "nan"])
def test_a_damaged_model_shows_the_page_s_message(damage, runs, page, cli, tmp_path):
    site = tmp_path / "site"
    code, _, err = cli("export", runs["gaussian"], "-f", "web", "-o", site)
    assert code == 0, err
    blob = bytearray((site / "model.bin").read_bytes())
    if damage == "truncated":
        blob = blob[: len(blob) // 2]
    elif damage == "header":
        blob[8:20] = b"not a header"
    else:
        size = int.from_bytes(blob[:8], "little")
        header = json.loads(blob[8:8 + size])
        begin = 8 + size + header["log_scales"]["data_offsets"][0]
        blob[begin:begin + 2] = np.array([np.nan], np.float16).tobytes()
    (site / "model.bin").write_bytes(bytes(blob))
    with serving(web_server(site, "127.0.0.1", 0)) as url:
        page.open(f"{url}index.html", 320, 240)
        root = "document.documentElement"
        state = page.wait_for(f"{root} && ({root}.getAttribute('data-error') || ({root}.hasAttribute('data-ready') && 'drawn'))",
                              "the page's verdict")
        shown = page.evaluate("document.body.innerText")
    assert state != "drawn", f"{damage}: the page drew a damaged model"
    assert "model.bin" in state and "model.bin" in shown


def test_view_serves_the_page(runs, tmp_path):
    """`radfield view RUN --port 0`: one line with the address, the page and model served from it,
    SIGTERM stops it with one line and exit 0."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    server = subprocess.Popen([sys.executable, "-m", "radfield", "view", str(runs["neural"]), "--port", "0"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = server.stderr.readline()
        assert line.startswith("viewer: http://127.0.0.1:") and "drawn by the browser" in line, line
        url = line.split()[1]
        assert b"<canvas" in urllib.request.urlopen(url + "index.html", timeout=30).read()
        assert urllib.request.urlopen(url + "model.bin", timeout=30).read()[:8]
        server.terminate()
        assert server.wait(timeout=30) == 0
        assert "viewer stopped" in server.stderr.read()
    finally:
        server.kill()


def test_the_page_shows_its_controls(runs, page, cli, tmp_path):
    """Without &ui=0: the panel with the dataset's cameras, the frames per second and each kind's
    own controls (a time slider and Play, light sliders); the screenshot of the neural model's page
    is docs/images/web-viewer.png (RADFIELD_KEEP_WEB_SCREENSHOT=PATH keeps it)."""
    controls = {"neural": [], "neural-dynamic": ["time-row", "play-row"],
                "neural-relight": ["azimuth-row", "elevation-row", "distance-row"]}
    for kind, rows in controls.items():
        site = tmp_path / kind
        code, _, err = cli("export", runs[kind], "-f", "web", "-o", site)
        assert code == 0, err
        with serving(web_server(site, "127.0.0.1", 0)) as url:
            page.open(f"{url}index.html", 720, 450)
            page.wait_ready()
            shown = page.evaluate("[...document.querySelectorAll('#panel, #panel .row')].filter(e => !e.hidden)"
                                  ".map(e => e.id).filter(Boolean)")
            cameras = page.evaluate("[...document.getElementById('cameras').options].map(o => o.textContent)")
            page.wait_for("document.getElementById('fps').textContent.includes('fps')", "the frames per second")
            image = page.screenshot()
        assert "panel" in shown and all(row in shown for row in rows), (kind, shown)
        hidden = {row for other in controls.values() for row in other} - set(rows)
        assert not hidden & set(shown), (kind, shown)
        assert len(cameras) == 4 and any("test" in c for c in cameras) and any("train" in c for c in cameras), cameras
        model = image[:, 260:]   # right of the panel
        assert (np.abs(model.astype(int) - model[0, -1].astype(int)).sum(-1) > 60).mean() > 0.02, kind
        if kind == "neural" and os.environ.get("RADFIELD_KEEP_WEB_SCREENSHOT"):
            cv2.imwrite(os.environ["RADFIELD_KEEP_WEB_SCREENSHOT"], cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
