"""`radfield export`: a model or a run in the formats other tools read (the work is in delivery/export.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield.cli.common import progress_bar, resolve_device, resolve_model
from radfield.errors import RadfieldError

EDIT_CAGE = Path("edit") / "cage.npz"    # an edited run's cage, in its edited pose
RUN_CAGE = Path("tetra") / "cage.npz"
RUN_ENVELOPE = Path("envelope") / "envelope.ply"
RUN_SCENE = Path("data") / "scene.json"
REFINE_STEPS = 300   # default --refine for a neural run: +6.8 dB held-out on the blobs demo, ~20 s on a CPU core


def load_content(target: Path, device: str = "cpu"):
    """A model file or a run directory as core.export.Content (the run's cage, envelope and cameras
    when it has them; why not, when it does not)."""
    from radfield.core.geometry.cage import read_cage
    from radfield.delivery.export import Content
    from radfield.delivery.io import load_model
    from radfield.datasets.scene import load_scene
    from radfield.core.geometry.envelope import read_envelope

    model = load_model(resolve_model(target), device=resolve_device(device))
    content = Content(model=model, source=str(target), missing={})
    if not target.is_dir():
        return content
    cage = next((target / p for p in (EDIT_CAGE, RUN_CAGE) if (target / p).is_file()), None)
    if cage is not None:
        content.cage = read_cage(cage)
    else:
        content.missing["cage"] = f"the run has no cage ({target / RUN_CAGE} is missing: the tetra stage has not run)"
    if (target / RUN_ENVELOPE).is_file():
        content.envelope = read_envelope(target / RUN_ENVELOPE)
    else:
        content.missing["envelope"] = f"the run has no envelope ({target / RUN_ENVELOPE} is missing)"
    if (target / RUN_SCENE).is_file():
        scene = load_scene(target / RUN_SCENE)
        content.background, content.extent = scene.background, scene.extent
        if scene.posed:
            content.views = scene.splits
        else:
            content.missing["cameras"] = "the run's photos are not posed yet (the sfm stage has not run)"
    else:
        content.missing["cameras"] = f"the run has no cameras ({target / RUN_SCENE} is missing)"
    return content


def export(
    target: Annotated[Path, typer.Argument(metavar="RUN_OR_MODEL", help="A run directory or a .safetensors model file (model files: ply-3dgs, splat, points only).")],
    format: Annotated[str, typer.Option("--format", "-f", help="ply-3dgs (3D-Gaussian PLY for 3DGS viewers), splat (antimatter15 .splat for web viewers), points (centres as a coloured point cloud PLY), cage (.vtk or .msh), envelope (PLY), cameras (nerfstudio transforms.json).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="File to write (.ply, .splat, .vtk, .msh or .json, as the format needs).")],
    components: Annotated[int, typer.Option(help="ply-3dgs/splat from neural primitives: Gaussians fitted to each primitive by moment matching.")] = 1,
    refine: Annotated[Optional[int], typer.Option(metavar="STEPS", help=f"ply-3dgs/splat from a neural run: optimise the moment-matched Gaussians this many steps against renders of the model from the run's training cameras (default {REFINE_STEPS} for a run, 0 for a model file; 0: moment matching only).")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite OUTPUT if it exists.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
):
    """Export a model or a run to a file other tools read, in the dataset's world frame.

    From a Gaussian model ply-3dgs and splat are exact; neural primitives are approximated by
    moment-matched Gaussians (--components per primitive), for a run refined against renders of
    the model (--refine). A model trained with render.supersample > 1 draws each pixel with n x n
    rays, which ply-3dgs/splat viewers cannot: a one-line warning on stderr."""
    from radfield.delivery.export import FORMATS, as_gaussians, check_target, export as export_content, supersample_warning
    from radfield.core.kinds.primitives import NeuralPrimitives

    if format not in FORMATS:
        raise RadfieldError(f"unknown --format {format!r} (choose one of {', '.join(FORMATS)})")
    if components < 1:
        raise RadfieldError(f"--components must be at least 1, got {components}")
    if refine is not None and refine < 0:
        raise RadfieldError(f"--refine must be 0 or more steps, got {refine}")
    check_target(format, output)
    if output.exists() and not force:
        raise RadfieldError(f"{output}: already exists (use --force to overwrite)")
    if output.is_dir():
        raise RadfieldError(f"{output}: is a folder, not a file")
    content = load_content(target)
    warning = supersample_warning(content.model, format)
    if warning:
        typer.echo(warning, err=True)
    how = None
    if format in ("ply-3dgs", "splat") and isinstance(content.model, NeuralPrimitives):
        steps = refine if refine is not None else (REFINE_STEPS if content.views else 0)
        if steps and not content.views:
            raise RadfieldError(f"{target}: --refine needs a run directory with cameras ({content.missing.get('cameras', 'a model file has none')})")
        gaussians = as_gaussians(content.model, components)
        if steps:
            gaussians = _refined(gaussians, content, steps, quiet)
        content.model = gaussians
        how = f"moment-matched neural primitives, {components} a primitive" + (f", refined {steps} steps" if steps else "")
    figures = export_content(content, format, output, components=components)
    if how:
        figures["from"] = how
    typer.echo(f"wrote {format} to {output} (" + ", ".join(f"{k} {v}" for k, v in figures.items()) + ")")


def _refined(gaussians, content, steps: int, quiet: bool):
    from radfield.delivery.export import view_cameras
    from radfield.delivery.moments import refine_gaussians
    from radfield.pipeline.config import load_config

    cameras = view_cameras(content.views["train"])
    with progress_bar(quiet) as progress:
        task = progress.add_task(f"refining {len(gaussians)} Gaussians on {len(cameras)} views", total=steps)
        return refine_gaussians(gaussians, content.model, cameras, load_config()["train"], steps=steps,
                                extent=content.extent or 1.0, background=content.background or (1.0, 1.0, 1.0),
                                on_step=lambda step, info: progress.update(task, completed=step))
