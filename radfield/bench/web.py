"""`radfield bench-web`: frames per second of the browser renderer (delivery/web/) in headless
Chromium, against radfield's own renderer on this machine in the same run.

For each primitive count and kind, the benchmark scene's model (bench/render.py: bench_models) is
exported as a web folder whose cameras are the orbit views of each size (bench_cameras), served
locally, and opened at each: the time from navigation to `data-ready` (fetching and parsing
model.bin, the textures, the first depth order and frame) is the page's start-up, which the page
splits (window.radfield.timings): "loaded" (fetch, parse, textures and programs, the first depth
order) and "first frame" (drawing it, waited for); then the page's
`radfield.bench(frames)` draws that many frames at the view, each waited for (gl.finish), and
reports the mean; radfield's renderer draws the same camera (`render_model`, no gradients) after
one untimed frame. Chromium runs its software GL (SwiftShader, on the CPU) unless `gpu`.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import torch

from radfield.bench.render import bench_cameras, bench_models
from radfield.core.render.antialias import render_model
from radfield.delivery.view_scene import ViewerScene
from radfield.delivery.web import write_site
from radfield.delivery.web.browser import headless_chromium
from radfield.delivery.web.serve import serving, web_server
from radfield.util.timing import clock

SIZES = ((256, 256), (800, 800), (1280, 720))


def run_bench_web(counts=(10_000, 100_000), kinds=("neural", "gaussian"), sizes=SIZES, frames: int = 5,
                  python: bool = True, gpu: bool = False, echo=print) -> list[dict]:
    """Print and return one row per (kind, count, size): the page's start-up seconds and frames per
    second, radfield's renderer's frames per second (None without `python`) and their ratio."""
    rows = []
    echo(f"bench-web: headless Chromium ({'its GPU' if gpu else 'software GL, SwiftShader'}), {frames} frames a view; "
         f"radfield's renderer with {torch.get_num_threads()} threads")
    echo(f"  {'kind':9s} {'primitives':>10s} {'view':>9s} {'page ready':>10s} {'loaded':>8s} {'1st frame':>9s} "
         f"{'browser':>12s} {'radfield':>12s} {'ratio':>7s}")
    with headless_chromium(gpu) as page:
        for num in counts:
            models = bench_models(num, tuple(kinds))
            for kind in kinds:
                model = models[kind]
                cameras = [bench_cameras(1, width, height)[0] for width, height in sizes]
                scene = ViewerScene(model, (1.0, 1.0, 1.0), splits={"orbit": cameras})
                with tempfile.TemporaryDirectory(prefix="radfield-bench-web-") as folder:
                    write_site(scene, Path(folder), title=f"bench {kind} {num}", check=False)
                    with serving(web_server(Path(folder), "127.0.0.1", 0)) as url:
                        for index, camera in enumerate(cameras):
                            start = time.perf_counter()
                            page.open(f"{url}index.html#view=orbit:{index}&ui=0", camera.width, camera.height)
                            page.wait_ready()
                            ready = time.perf_counter() - start
                            parts = page.evaluate("window.radfield.timings") or {}
                            loaded = sum(parts.get(key) or 0.0 for key in ("fetch_ms", "parse_ms", "upload_ms", "sort_ms")) / 1e3
                            first = (parts.get("first_frame_ms") or 0.0) / 1e3
                            measured = page.evaluate(f"window.radfield.bench({frames})")
                            ours = python_fps(model, camera) if python else None
                            row = {"kind": kind, "primitives": num, "width": camera.width, "height": camera.height,
                                   "ready_s": ready, "loaded_s": loaded, "first_frame_s": first, "timings": parts,
                                   "browser_fps": measured["fps"], "python_fps": ours}
                            rows.append(row)
                            ratio = f"{row['browser_fps'] / ours:6.1f}x" if ours else "      -"
                            theirs = f"{ours:8.2f} FPS" if ours else "           -"
                            echo(f"  {kind:9s} {num:10d} {camera.width:4d}x{camera.height:<4d} {ready:9.2f}s {loaded:7.2f}s {first:8.2f}s "
                                 f"{row['browser_fps']:8.2f} FPS {theirs} {ratio}")
    return rows


def python_fps(model, camera, repeats: int = 2) -> float:
    """radfield's renderer's frames per second at `camera` (after one untimed frame)."""
    with torch.no_grad():
        render_model(model, camera)
        start = clock("cpu")
        for _ in range(repeats):
            render_model(model, camera)
        return repeats / (clock("cpu") - start)
