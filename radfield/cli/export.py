"""`radfield export`: a model or a run in the formats other tools read (the work: radfield.delivery.export,
radfield.delivery.content)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield.cli.common import check_output, condition_options
from radfield.errors import RadfieldError

# The default export of a neural run (issue 28; docs/studies/export-fidelity.md): 2 Gaussians a
# primitive refined 2000 steps against the model's renders from the training cameras and as many
# orbit views, with densification; within 1 dB of the run's own held-out PSNR on the demo scenes
# (300 steps of one Gaussian a primitive lost 1.5-2.8 dB), 20-40 s a 64×64 scene on a CPU core.
REFINE_STEPS = 2000
REFINE_COMPONENTS = 2   # a model file (no cameras, moment matching only) keeps 1: more are worse unrefined
WEB = "web"             # a folder, not a file: the browser renderer (radfield.delivery.web)


@condition_options("export")
def export(
    target: Annotated[Path, typer.Argument(metavar="RUN_OR_MODEL", help="A run directory or a model file: radfield's .safetensors or any format `radfield import` reads (model files: ply-3dgs, splat, spz, glb, points, web only).")],
    format: Annotated[str, typer.Option("--format", "-f", help="ply-3dgs (3D-Gaussian PLY for 3DGS viewers), splat (antimatter15 .splat for web viewers), spz (Niantic SPZ version 3, about a tenth of a PLY, quantised), glb (glTF 2.0 binary with KHR_gaussian_splatting), points (centres as a coloured point cloud PLY), cage (.vtk or .msh), envelope (PLY), cameras (nerfstudio transforms.json), web (a folder with a page that draws the model in the browser, WebGL2).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="File to write (.ply, .splat, .spz, .glb, .vtk, .msh or .json, as the format needs); for web a folder.")],
    components: Annotated[Optional[int], typer.Option(help=f"ply-3dgs/splat/spz/glb from neural primitives: Gaussians fitted to each primitive by moment matching (default {REFINE_COMPONENTS} for a refined run, 1 otherwise).")] = None,
    refine: Annotated[Optional[int], typer.Option(metavar="STEPS", help=f"ply-3dgs/splat/spz/glb from a neural run: optimise the moment-matched Gaussians this many steps against renders of the model from the run's training cameras and as many random views around the object, with 3DGS densification (default {REFINE_STEPS} for a run, 0 for a model file; 0: moment matching only).")] = None,
    asked=None,   # the view conditions' options (cli/common.condition_options: --time, --light, ...)
    force: Annotated[bool, typer.Option("--force", help="Overwrite OUTPUT if it exists.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
):
    """Export a model or a run to a file other tools read, in the dataset's world frame.

    From a Gaussian model ply-3dgs and glb are exact, splat and spz quantised (the line reports the
    file read back against the Gaussians written, PSNR at the run's test views); neural primitives
    are approximated by moment-matched Gaussians (--components per primitive), for a run refined
    against renders of the model (--refine). A model trained with render.supersample > 1 draws each
    pixel with n x n rays, which ply-3dgs/splat/spz/glb viewers cannot: a one-line warning on
    stderr. A dynamic model is exported at one moment: --time T; a relightable model under one light: --light X,Y,Z (or
    --light-dir X,Y,Z). web writes a folder (index.html, the renderer, view.json, model.bin) that
    any static web host serves: the page draws every kind from its own parameters, a dynamic
    model with a time slider and a relightable one with light sliders (--time/--light: where they
    start), and opens at the run's first test camera."""
    from radfield import conditions
    from radfield.delivery.content import file_fidelity, gaussians_for, load_content, parts_for, under_conditions
    from radfield.delivery.export import (FORMATS, GAUSSIAN_FORMATS, as_gaussians, check_target, export as export_content,
                                          supersample_warning)

    if format == WEB:
        return _export_web(target, output, asked, force)
    if format not in FORMATS:
        raise RadfieldError(f"unknown --format {format!r} (choose one of {', '.join(FORMATS + (WEB,))})")
    if components is not None and components < 1:
        raise RadfieldError(f"--components must be at least 1, got {components}")
    if refine is not None and refine < 0:
        raise RadfieldError(f"--refine must be 0 or more steps, got {refine}")
    check_target(format, output)
    check_output(output, force, folder=False)   # the output policy of every command (docs/usage.md, 'Outputs')
    content = load_content(target, parts=parts_for(format))
    kind = content.model.kind
    values = under_conditions(content, format, asked)   # a conditioned model: its static model of those values
    warning = supersample_warning(content.model, format)
    if warning:
        typer.echo(warning, err=True)
    steps = refine if refine is not None else (REFINE_STEPS if content.views else 0)
    components = components or (REFINE_COMPONENTS if steps else 1)
    made = gaussians_for(content, format, components, steps, quiet)
    figures = export_content(content, format, output, components=components)
    if made:
        figures["from"] = made.how
    for name, value in values.items():
        figures.update(conditions.get(name).figures(value))
    if values and not made and "from" in figures:
        figures["from"] = kind
    if format in GAUSSIAN_FORMATS:   # what the file format loses: the file read back against its Gaussians
        psnr, views, split = file_fidelity(as_gaussians(content.model, components), output, format, content)
        figures["read back"] = (f"{psnr:.2f} dB" if psnr < 99 else "lossless") + f" against the Gaussians on {views} {split} views"
    typer.echo(f"wrote {format} to {output} (" + ", ".join(f"{k} {v}" for k, v in figures.items()) + ")")
    if made:
        for line in made.report():
            typer.echo(line)


def _export_web(target: Path, output: Path, asked, force: bool) -> None:
    """The web folder (radfield.delivery.web) of a run or a model file."""
    from radfield.delivery.view_scene import viewer_scene
    from radfield.delivery.web import write_site

    check_output(output, force, folder=True)
    figures = write_site(viewer_scene(target, asked=asked), output, title=target.name)
    typer.echo(f"wrote web to {output} (" + ", ".join(f"{k} {v}" for k, v in figures.items()) + "); "
               f"serve the folder over http (radfield view {target} does)")
