"""What `radfield export` and `radfield view` show of a model file or a run directory: the model, and
for a run its cage, envelope, cameras, background and extent (radfield.delivery.export.Content;
the run's files are found through radfield.run.Run).

Only the parts asked for are read, so that exporting a model from a run does not need the
envelope's mesh library (pymeshlab); a part a run lacks is None, and `Content.missing` says why.
"""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path

from radfield.delivery.export import ONE_RAY_FORMATS, Content
from radfield.errors import RadfieldError
from radfield.run import Run, model_file
from radfield.util.progress import progress_bar

PARTS = ("cage", "envelope", "cameras")


def load_content(target: Path, device: str = "cpu", parts: Collection[str] = PARTS) -> Content:
    """A model file or a run directory as Content: the model on `device`, and for a run the `parts`
    (of PARTS) it has; background and extent come with the cameras."""
    from radfield.delivery.io import load_model

    model = load_model(model_file(target), device=device)
    content = Content(model=model, source=str(target), missing={})
    if not target.is_dir():
        return content
    run = Run(target)
    if "cage" in parts:
        _load_cage(run, content)
    if "envelope" in parts:
        _load_envelope(run, content)
    if "cameras" in parts:
        _load_cameras(run, content)
    return content


def _load_cage(run: Run, content: Content) -> None:
    from radfield.core.geometry.cage import read_cage

    if run.cage is not None:
        content.cage = read_cage(run.cage)
    else:
        content.missing["cage"] = f"the run has no cage ({run.reconstructed_cage} is missing: the tetra stage has not run)"


def _load_envelope(run: Run, content: Content) -> None:
    if run.envelope.is_file():
        from radfield.core.geometry.envelope import read_envelope

        content.envelope = read_envelope(run.envelope)
    else:
        content.missing["envelope"] = f"the run has no envelope ({run.envelope} is missing)"


def _load_cameras(run: Run, content: Content) -> None:
    from radfield.datasets.scene import load_scene

    if run.scene.is_file():
        scene = load_scene(run.scene)
        content.background, content.extent = scene.background, scene.extent
        if scene.posed:
            content.views = scene.splits
        else:
            content.missing["cameras"] = "the run's photos are not posed yet (the sfm stage has not run)"
    else:
        content.missing["cameras"] = f"the run has no cameras ({run.scene} is missing)"


def parts_for(format: str) -> tuple[str, ...]:
    """The parts of a run an export `format` reads: its own, and the cameras (with background and
    extent) that refine the Gaussians of ply-3dgs and splat."""
    return {"cage": ("cage",), "envelope": ("envelope",), "points": ()}.get(format, ("cameras",))


def gaussians_for(content: Content, format: str, components: int, steps: int, quiet: bool = True) -> str | None:
    """For a ply-3dgs or splat `format` of neural primitives: replace content.model by Gaussians
    moment-matched to them (`components` a primitive), refined `steps` steps against renders of the
    model from the run's training cameras (0: moment matching only). Returns how the Gaussians
    were made, for the report; None when the model is left as it is."""
    from radfield.core import kinds
    from radfield.delivery.export import as_gaussians

    if format not in ONE_RAY_FORMATS or kinds.of(content.model).exact_gaussians:
        return None
    if steps and not content.views:
        raise RadfieldError(f"{content.source}: --refine needs a run directory with cameras "
                            f"({content.missing.get('cameras', 'a model file has none')})")
    gaussians = as_gaussians(content.model, components)
    if steps:
        gaussians = refined(gaussians, content, steps, quiet)
    content.model = gaussians
    return f"moment-matched neural primitives, {components} a primitive" + (f", refined {steps} steps" if steps else "")


def refined(gaussians, content: Content, steps: int, quiet: bool = True):
    """`gaussians` optimised `steps` steps against renders of content.model from the run's training
    cameras (radfield.delivery.moments.refine_gaussians, with the defaults' train settings)."""
    from radfield.delivery.export import view_cameras
    from radfield.delivery.moments import refine_gaussians
    from radfield.pipeline.config import load_config

    cameras = view_cameras(content.views["train"])
    with progress_bar(quiet) as progress:
        task = progress.add_task(f"refining {len(gaussians)} Gaussians on {len(cameras)} views", total=steps)
        return refine_gaussians(gaussians, content.model, cameras, load_config()["train"], steps=steps,
                                extent=content.extent or 1.0, background=content.background or (1.0, 1.0, 1.0),
                                on_step=lambda step, info: progress.update(task, completed=step))
