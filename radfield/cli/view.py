"""`radfield view`: the browser viewer (radfield.delivery.viewer) of a run or a model file."""

from __future__ import annotations

import signal
from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield.cli.common import condition_options, parse_background, resolve_device
from radfield.errors import RadfieldError


@condition_options("view")
def view(
    target: Annotated[Path, typer.Argument(metavar="RUN_OR_MODEL", help="A run directory (model, cage and cameras) or a .safetensors model file.")],
    port: Annotated[int, typer.Option(help="TCP port of the web viewer (the next free one if it is taken; 0: any free port).")] = 8080,
    host: Annotated[str, typer.Option(help="Address to listen on (127.0.0.1: this machine only; 0.0.0.0: every network).")] = "127.0.0.1",
    resolution: Annotated[int, typer.Option(help="Long side, in pixels, of the frames rendered once the camera rests.")] = 512,
    moving_downscale: Annotated[int, typer.Option(help="Frames rendered while the camera moves are this many times smaller.")] = 4,
    background: Annotated[Optional[str], typer.Option(help="Background R,G,B in [0, 1] (default: the run's, else 1,1,1).")] = None,
    device: Annotated[str, typer.Option(help="cpu or cuda: where the model is rendered.")] = "cpu",
    asked=None,   # the view conditions' options (cli/common.condition_options: --time, --light, ...)
):
    """Open an interactive viewer of a model in the browser, rendered on this machine.

    The page (http://HOST:PORT) shows frames drawn by radfield's renderer here, the run's cage as
    a wireframe toggle and its cameras as frustums; for a dynamic model a Time slider and a Play
    button, for a relightable model light sliders (azimuth, elevation, distance). Stop it with
    Ctrl-C (or SIGTERM: one line, exit 0)."""
    from radfield.delivery.viewer import Viewer, viewer_scene

    if not 0 <= port < 65536:
        raise RadfieldError(f"--port must be in 0..65535, got {port}")
    if resolution < 16 or moving_downscale < 1:
        raise RadfieldError("--resolution must be at least 16 and --moving-downscale at least 1")
    resolve_device(device)
    scene = viewer_scene(target, device, parse_background(background) if background is not None else None, asked)
    try:
        viewer = Viewer(scene, host=host, port=port, resolution=resolution, moving_downscale=moving_downscale,
                        log=lambda line: typer.echo(line, err=True))
    except OSError as error:
        raise RadfieldError(f"cannot listen on {host}:{port} ({error.strerror or error})") from None
    typer.echo(f"viewer: http://{host}:{viewer.server.get_port()} ({len(scene.model)} {scene.model.kind} primitives, "
               f"{len(scene.cameras)} cameras{', a time slider and Play' if viewer.dynamic else ''}"
               f"{', light sliders' if viewer.relightable else ''}); Ctrl-C stops it",
               err=True)
    # SIGTERM (systemd, docker stop, kill) stops the viewer like Ctrl-C, with one line and exit 0:
    # by default it killed the process without closing the server, and a library that installs
    # glog's failure handler (pycolmap) turned it into a 32-line stack dump
    signal.signal(signal.SIGTERM, _terminate)
    try:
        viewer.serve_forever()   # its `finally` stops the server
    except _Terminated:
        typer.echo("radfield: viewer stopped (SIGTERM)", err=True)


class _Terminated(Exception):
    """Raised in the main thread by the SIGTERM handler."""


def _terminate(signum, frame) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)   # a second SIGTERM while stopping kills at once
    raise _Terminated()
