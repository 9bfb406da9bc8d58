"""`radfield view`: a run or a model file in the browser, drawn there by the browser renderer
(radfield.delivery.web: the web export, served from this machine), or with --server frame by frame
by radfield's renderer here (radfield.delivery.viewer)."""

from __future__ import annotations

import signal
import tempfile
import threading
from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield import conditions
from radfield.cli.common import condition_options, parse_background, resolve_device
from radfield.errors import RadfieldError


@condition_options("view")
def view(
    target: Annotated[Path, typer.Argument(metavar="RUN_OR_MODEL", help="A run directory (model, cage and cameras) or a model file (radfield's .safetensors, or any format `radfield import` reads).")],
    port: Annotated[int, typer.Option(help="TCP port of the web viewer (the next free one if it is taken; 0: any free port).")] = 8080,
    host: Annotated[str, typer.Option(help="Address to listen on (127.0.0.1: this machine only; 0.0.0.0: every network).")] = "127.0.0.1",
    server: Annotated[bool, typer.Option("--server", help="Render every frame here with radfield's renderer and stream it (exact pixels, any model size, slower) instead of in the browser.")] = False,
    resolution: Annotated[int, typer.Option(help="--server: long side, in pixels, of the frames rendered once the camera rests.")] = 512,
    moving_downscale: Annotated[int, typer.Option(help="--server: frames rendered while the camera moves are this many times smaller.")] = 4,
    background: Annotated[Optional[str], typer.Option(help="Background R,G,B in [0, 1] (default: the run's, else 1,1,1).")] = None,
    device: Annotated[str, typer.Option(help="--server: cpu or cuda, where the model is rendered.")] = "cpu",
    asked=None,   # the view conditions' options (cli/common.condition_options: --time, --light, ...)
):
    """Open an interactive viewer of a model in the browser.

    By default the browser draws the model itself on its GPU (WebGL2), as `radfield export -f web`
    writes it, served from this machine (http://HOST:PORT): orbit and fly controls, the dataset's
    cameras to jump to, a time slider and Play for a dynamic model, light sliders (azimuth,
    elevation, distance) for a relightable one, frames per second, a link to the current view.
    --time/--light choose where those controls start. With --server every frame is rendered here
    by radfield's renderer and streamed to the page (the run's cage as a wireframe toggle, its
    cameras as frustums). Stop it with Ctrl-C (or SIGTERM: one line, exit 0)."""
    from radfield.delivery.view_scene import viewer_scene

    if not 0 <= port < 65536:
        raise RadfieldError(f"--port must be in 0..65535, got {port}")
    if resolution < 16 or moving_downscale < 1:
        raise RadfieldError("--resolution must be at least 16 and --moving-downscale at least 1")
    resolve_device(device)
    scene = viewer_scene(target, device if server else "cpu",
                         parse_background(background) if background is not None else None, asked)
    if not server:
        return _view_in_browser(scene, target, host, port)
    from radfield.delivery.viewer import Viewer

    try:
        viewer = Viewer(scene, host=host, port=port, resolution=resolution, moving_downscale=moving_downscale,
                        log=lambda line: typer.echo(line, err=True))
    except OSError as error:
        raise RadfieldError(f"cannot listen on {host}:{port} ({error.strerror or error})") from None
    typer.echo(f"viewer: http://{host}:{viewer.server.get_port()} ({len(scene.model)} {scene.model.kind} primitives, "
               f"{len(scene.cameras)} cameras{', a time slider and Play' if viewer.dynamic else ''}"
               f"{', light sliders' if viewer.relightable else ''}); Ctrl-C stops it",
               err=True)
    _serve_until_stopped(viewer.serve_forever)   # its `finally` stops the server


def _view_in_browser(scene, target: Path, host: str, port: int) -> None:
    """Write the web export of `scene` into a temporary folder and serve it until stopped."""
    from radfield.delivery.web import write_site
    from radfield.delivery.web.serve import serving, web_server

    with tempfile.TemporaryDirectory(prefix="radfield-view-") as folder:
        figures = write_site(scene, Path(folder), title=target.name)
        try:
            httpd = web_server(Path(folder), host, port)
        except OSError as error:
            raise RadfieldError(f"cannot listen on {host}:{port} ({error.strerror or error})") from None
        with serving(httpd) as url:
            taken = [condition.name for condition in conditions.taken(scene.model)]
            typer.echo(f"viewer: {url} ({len(scene.model)} {scene.model.kind} primitives drawn by the browser, "
                       f"{figures['precision']}, {sum(map(len, scene.splits.values()))} cameras"
                       f"{', a time slider and Play' if 'time' in taken else ''}"
                       f"{', light sliders' if 'light' in taken else ''}); Ctrl-C stops it", err=True)
            _serve_until_stopped(threading.Event().wait)


def _serve_until_stopped(serve) -> None:
    """Run `serve` until Ctrl-C or SIGTERM. SIGTERM (systemd, docker stop, kill) stops the viewer
    like Ctrl-C, with one line and exit 0: by default it killed the process without closing the
    server, and a library that installs glog's failure handler (pycolmap) turned it into a 32-line
    stack dump."""
    signal.signal(signal.SIGTERM, _terminate)
    try:
        serve()
    except _Terminated:
        typer.echo("radfield: viewer stopped (SIGTERM)", err=True)


class _Terminated(Exception):
    """Raised in the main thread by the SIGTERM handler."""


def _terminate(signum, frame) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)   # a second SIGTERM while stopping kills at once
    raise _Terminated()
