"""`radfield animate`: a sequence of cage poses (cage files, or the built-in soft-body simulation)
of a run rendered to PNG frames and an MP4 (the work: radfield.edit.animate)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield.cli.common import Force, check_options, check_output, parse_background, resolve_device
from radfield.errors import RadfieldError
from radfield.util.ranges import AT_LEAST_0, AT_LEAST_1, ELEVATION, POSITIVE


def animate(
    run: Annotated[Path, typer.Argument(metavar="RUN", help="A run directory with a cage (reconstructed or edited).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder to create: frame_NNNN.png, animation.mp4, animation.json (an existing non-empty one needs --force).")],
    cages: Annotated[Optional[str], typer.Option(help="Cage poses: a folder of .vtk/.vtu/.msh/.npz frames or a glob pattern (same topology as the run's cage, world frame).")] = None,
    simulate: Annotated[Optional[Path], typer.Option(help="Instead of --cages: a YAML file with a 'simulate:' mapping (built-in soft-body simulation, docs/usage.md 'Animation').")] = None,
    spec: Annotated[Optional[Path], typer.Option("--spec", "-s", help="Instead of --cages/--simulate: a YAML animation spec, 'animate: {cages: PATTERN, camera: ..., fps: ...}' and/or 'simulate: {...}'; its keys replace the options of the same name (docs/usage.md 'Animation').")] = None,
    dataset: Annotated[Optional[Path], typer.Option("--dataset", "-d", help="Dataset whose camera to use (default: the run's).")] = None,
    split: Annotated[str, typer.Option(help="Split of the dataset camera.")] = "test",
    camera: Annotated[str, typer.Option(help="The dataset view to render from: its frame name, or its index in the split.")] = "0",
    orbit: Annotated[bool, typer.Option("--orbit", help="Turn the camera once around the scene over the animation.")] = False,
    elevation: Annotated[float, typer.Option(help="Orbit elevation in degrees.")] = 20.0,
    downscale: Annotated[int, typer.Option(help="Render at 1/K of the dataset's resolution.")] = 1,
    background: Annotated[Optional[str], typer.Option(help="Background R,G,B (default: the run's, else 1,1,1).")] = None,
    fps: Annotated[Optional[float], typer.Option(help="Video frame rate.", show_default="30, or the simulation's")] = None,
    gradient: Annotated[str, typer.Option(help="Per-primitive map from the cage: smooth, centre or tet (docs/usage.md 'How primitives follow the cage').")] = "smooth",
    split_threshold: Annotated[float, typer.Option("--split-threshold", help="Split primitives straddling non-uniform tets (0: never).")] = 0.5,
    device: Annotated[str, typer.Option(help="cpu or cuda.")] = "cpu",
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
    force: Force = False,
):
    """Render a sequence of cage poses of a run frame by frame to PNGs and an MP4.

    The poses: cage files (a soft-body simulation exported from Houdini or Blender, say), or the
    built-in simulation.

    Every frame deforms the run's field exactly from its rest cage to the frame's cage (as
    `radfield edit` with a deform operation), then renders it from one dataset camera or an orbit.
    --spec FILE holds the same as a file: 'animate: {cages: PATTERN, camera: 0, fps: 30, ...}' or
    'simulate: {...}' (with an optional 'animate:' of render settings)."""
    from radfield.edit.animate import VIDEO, animate as animate_run
    from radfield.edit.source import load_source
    from radfield.run import is_run_dir

    check_options({"--elevation": (elevation, ELEVATION), "--downscale": (downscale, AT_LEAST_1),
                   "--fps": (fps, POSITIVE), "--split-threshold": (split_threshold, AT_LEAST_0)})
    if sum(x is not None for x in (cages, simulate, spec)) != 1:
        raise RadfieldError("give exactly one of --cages, --simulate and --spec")
    simulation, camera_option = simulate, "--camera"
    if spec is not None:
        from radfield.edit.animation_spec import read_animation

        anim = read_animation(spec)
        cages, simulation = anim["cages"], anim["simulate"]
        camera, split, orbit = anim.get("camera", camera), anim.get("split", split), anim.get("orbit", orbit)
        camera_option = f"{spec}: animate.camera" if "camera" in anim else camera_option
        elevation, fps, downscale = anim.get("elevation", elevation), anim.get("fps", fps), anim.get("downscale", downscale)
        background, gradient = anim.get("background", background), anim.get("gradient", gradient)
        split_threshold = anim.get("split_threshold", split_threshold)
    check_output(output, force, folder=True)
    if not is_run_dir(run):
        raise RadfieldError(f"{run}: not a radfield run directory")
    dev = resolve_device(device)
    fld = load_source(run)
    if not fld.has_cage:
        raise RadfieldError(f"{run}: this run has no cage to animate")
    summary = animate_run(run, fld, output, cages=cages, simulation=simulation, dataset=dataset, split=split,
                          camera=camera, camera_option=camera_option, orbit=orbit, elevation=elevation, downscale=downscale,
                          background=parse_background(background) if background is not None else None, fps=fps or 0.0,
                          gradient=gradient, split_threshold=split_threshold, device=dev, quiet=quiet,
                          log=None if quiet else (lambda m: typer.echo(m, err=True)))
    flicker = (f", mean PSNR between consecutive frames {summary['consecutive_psnr']:.2f} dB"
               if summary["consecutive_psnr"] is not None else "")
    typer.echo(f"animated {summary['frames']} frames ({summary['width']}x{summary['height']}) to {output / VIDEO}: "
               f"{summary['render_ms']:.1f} ms/frame render, {summary['deform_ms']:.1f} ms/frame deform{flicker}")
