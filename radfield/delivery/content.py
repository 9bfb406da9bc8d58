"""What `radfield export` and `radfield view` show of a model file or a run directory: the model, and
for a run its cage, envelope, cameras, background and extent (radfield.delivery.export.Content;
the run's files are found through radfield.run.Run).

Only the parts asked for are read, so that exporting a model from a run does not need the
envelope's mesh library (pymeshlab); a part a run lacks is None, and `Content.missing` says why.
A conditioned model is exported under one value of each condition (`under_conditions`: the static
model of `--time T`, of `--light X,Y,Z`).
"""

from __future__ import annotations

import functools
from collections.abc import Collection
from pathlib import Path
from typing import Any, NamedTuple

import torch

from radfield import conditions
from radfield.delivery.export import ONE_RAY_FORMATS, Content
from radfield.core.kinds.moment_matching import MIN_OPACITY
from radfield.errors import RadfieldError
from radfield.run import Run, model_file
from radfield.util.progress import progress_bar

PARTS = ("cage", "envelope", "cameras")
ORBIT_VIEWS = 100   # at most this many random views besides the training cameras refine a neural export


def load_content(target: Path, device: str = "cpu", parts: Collection[str] = PARTS) -> Content:
    """A model file or a run directory as Content: the model on `device`, and for a run the `parts`
    (of PARTS) it has; background and extent come with the cameras."""
    from radfield.model_formats import load

    model = load(model_file(target), device=device)
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


def under_conditions(content: Content, format: str, asked: dict[str, conditions.Asked]) -> dict[str, Any]:
    """A conditioned model is exported under one value of each condition its kind reads (issues 29,
    30): content.model becomes the static model of those values (its kind's at_conditions: at_time,
    eq. 10-13; at_light, SH of degree 3 fitted over view directions) before any conversion, so
    that moment matching, refinement (whose teacher renders the run's training cameras, each with
    its own conditions) and the fidelity figure all see that model. A conditioned model without a
    value, a value for a model whose kind does not read it or for a format that holds no model, or
    a point light inside the run's object bounds: one error line. Each value resolved against the
    run's views (a light as bright as its dataset's). Returns the values used."""
    from radfield.delivery.export import MODEL_FORMATS, view_cameras

    for name, request in asked.items():
        if format not in MODEL_FORMATS:
            raise RadfieldError(f"{request.option} is for the exports of a model ({', '.join(MODEL_FORMATS)}), not {format}")
        conditions.check_takes(content.model, content.source, name, request.option)
    if format in MODEL_FORMATS:
        for condition in conditions.taken(content.model):
            if condition.name not in asked:
                raise RadfieldError(f"{content.source}: the model is {condition.model_words} ({content.model.kind}) and "
                                    f"{format} holds {condition.once}: give {condition.value_words} ({condition.how_once})")
    if not asked:
        return {}
    cameras = view_cameras([view for views in (content.views or {}).values() for view in views])
    bounds = functools.cache(lambda: run_bounds(content))
    values = {name: conditions.get(name).resolved(request, cameras, bounds).value for name, request in asked.items()}
    content.model = conditions.fixed(content.model, values)
    return values


def run_bounds(content: Content):
    """The object's bounds of a run's dataset (delivery/render_views.py: dataset_bounds), None for a
    model file or a run without cameras or dataset."""
    from radfield.delivery.export import view_cameras
    from radfield.delivery.render_views import dataset_bounds

    if not content.views or not Path(content.source).is_dir():
        return None
    cameras = view_cameras([view for views in content.views.values() for view in views])
    return dataset_bounds(cameras, Run(Path(content.source)).dataset())


def parts_for(format: str) -> tuple[str, ...]:
    """The parts of a run an export `format` reads: its own, and the cameras (with background and
    extent) that refine the Gaussians of the Gaussian formats (ply-3dgs, splat, spz, glb) and
    measure what their file loses."""
    return {"cage": ("cage",), "envelope": ("envelope",), "points": ()}.get(format, ("cameras",))


class Conversion(NamedTuple):
    """How `gaussians_for` made the Gaussians of a neural model, for the export's report."""

    how: str                          # one phrase for the "wrote …" line
    dropped: int                      # moment-matched components left out (opacity < MIN_OPACITY)
    fidelity: tuple[float, int, str] | None   # (PSNR dB, views, split) of the Gaussians against the model

    def report(self) -> list[str]:
        lines = []
        if self.dropped:
            lines.append(f"left out {self.dropped} moment-matched Gaussians fainter than opacity {MIN_OPACITY:g} "
                         "(they would not change a pixel by 1/255)")
        if self.fidelity is not None:
            psnr, views, split = self.fidelity
            lines.append(f"the Gaussians against the model's own renders: {psnr:.2f} dB PSNR on {views} {split} views "
                         "(one ray a pixel, as other tools draw them)")
        return lines


def gaussians_for(content: Content, format: str, components: int, steps: int, quiet: bool = True) -> Conversion | None:
    """For a Gaussian `format` (ply-3dgs, splat, spz, glb) of neural primitives: replace content.model by Gaussians
    moment-matched to them (`components` a primitive), refined `steps` steps against renders of the
    model from the run's training cameras and orbit views, with densification (0: moment matching
    only), and measure them against the model on the run's test views. None when the model is
    left as it is (Gaussians are exported exactly)."""
    from radfield.core import kinds
    from radfield.delivery.export import as_gaussians

    if format not in ONE_RAY_FORMATS or kinds.of(content.model).exact_gaussians:
        return None
    if steps and not content.views:
        raise RadfieldError(f"{content.source}: --refine needs a run directory with cameras "
                            f"({content.missing.get('cameras', 'a model file has none')})")
    teacher = content.model
    gaussians = as_gaussians(teacher, components)
    dropped = components * len(teacher) - len(gaussians)
    if steps:
        gaussians = refined(gaussians, content, steps, quiet)
    content.model = gaussians
    how = f"moment-matched neural primitives, {components} a primitive" + (f", refined {steps} steps" if steps else "")
    return Conversion(how, dropped, fidelity(gaussians, teacher, content))


def fidelity(gaussians, teacher, content: Content) -> tuple[float, int, str] | None:
    """Mean PSNR of the Gaussians drawn with one ray a pixel against the model's own renders, over
    the run's test views (train views when it has none), each camera once (`static_views`); None
    for a model file."""
    from radfield.core.render.antialias import render_model
    from radfield.core.render.rasterize import render

    if not content.views:
        return None
    split = next((s for s in ("test", "val", "train") if content.views.get(s)), None)
    if split is None:
        return None
    background = content.background or (1.0, 1.0, 1.0)
    values = []
    with torch.no_grad():
        for camera in static_views(content.views[split], teacher):
            truth = render_model(teacher, camera, background=background).color.clamp(0, 1)
            mine = render(gaussians, camera, background=background).color.clamp(0, 1)
            values.append(float(-10 * torch.log10(((mine - truth) ** 2).mean().clamp_min(1e-12))))
    return sum(values) / len(values), len(values), split


FILE_VIEWS = 8   # at most this many of the run's test views measure a file's quantisation


def file_fidelity(written, path: Path, format: str, content: Content) -> tuple[float, int, str]:
    """What the file format lost: mean PSNR of the Gaussians read back from `path` (radfield.model_formats)
    against the Gaussians `written` to it, both drawn one ray a pixel, at up to FILE_VIEWS of the
    run's test views (val, then train, where it has none), or for a model file at 4 views of 64 × 64
    around the model (`probe_cameras`). Returns (PSNR dB, views, split); PSNR is capped at 99 dB
    (a lossless format)."""
    from radfield import model_formats
    from radfield.core.render.rasterize import render

    back = model_formats.get(format).read(path)
    split = next((s for s in ("test", "val", "train") if (content.views or {}).get(s)), None)
    if split is None:
        cameras, split = probe_cameras(written), "orbit"
    else:
        cameras = static_views(content.views[split], written)
        cameras = [cameras[round(i)] for i in torch.linspace(0, len(cameras) - 1, min(FILE_VIEWS, len(cameras))).tolist()]
    background = content.background or (1.0, 1.0, 1.0)
    values = []
    with torch.no_grad():
        for camera in cameras:
            truth = render(written, camera, background=background).color.clamp(0, 1)
            mine = render(back, camera, background=background).color.clamp(0, 1)
            values.append(min(99.0, float(-10 * torch.log10(((mine - truth) ** 2).mean().clamp_min(1e-12)))))
    return sum(values) / len(values), len(values), split


def probe_cameras(model, count: int = 4, size: int = 64) -> list:
    """`count` views of size × size pixels around a model without cameras: from 3× the radius that
    holds 90% of its centres, about its median centre, at 20° above and below the equator in turn
    (z up), a 50° field of view."""
    import math

    from radfield.core.geometry.cameras import Camera, look_at

    means = model.means.detach().to("cpu", torch.float64)
    centre = means.median(0).values
    radius = float(torch.quantile((means - centre).norm(dim=-1), 0.9)) or 1.0
    focal = 0.5 * size / math.tan(math.radians(25))
    cameras = []
    for i in range(count):
        azimuth, elevation = 2 * math.pi * i / count, math.radians(20 if i % 2 == 0 else -20)
        eye = centre + 3 * radius * torch.tensor([math.cos(azimuth) * math.cos(elevation),
                                                 math.sin(azimuth) * math.cos(elevation), math.sin(elevation)],
                                                dtype=torch.float64)
        cameras.append(Camera(focal, focal, size / 2, size / 2, size, size, look_at(eye, centre), f"probe_{i}"))
    return cameras


def static_views(views: list[dict], model) -> list:
    """The cameras of scene.json `views` as a static model sees them: each pose once. A dynamic or
    relighting dataset holds every camera at each of its moments or lights, which the static model
    of one moment or light (under_conditions) draws the same: measured once, not 24 times."""
    from radfield.core import kinds
    from radfield.core.geometry.cameras import distinct_poses
    from radfield.delivery.export import view_cameras

    cameras = view_cameras(views)
    return cameras if kinds.of(model).conditions else distinct_poses(cameras)[0]


def refined(gaussians, content: Content, steps: int, quiet: bool = True):
    """`gaussians` optimised `steps` steps against renders of content.model from the run's training
    cameras and as many orbit views (up to ORBIT_VIEWS), with densification
    (radfield.delivery.refine.refine_gaussians, with the defaults' train settings)."""
    from radfield.delivery.refine import refine_gaussians
    from radfield.pipeline.config import load_config

    cameras = static_views(content.views["train"], content.model)
    orbit = min(len(cameras), ORBIT_VIEWS)
    with progress_bar(quiet) as progress:
        task = progress.add_task(f"refining {len(gaussians)} Gaussians on {len(cameras) + orbit} views", total=steps)
        return refine_gaussians(gaussians, content.model, cameras, load_config()["train"], steps=steps,
                                extent=content.extent or 1.0, background=content.background or (1.0, 1.0, 1.0),
                                orbit=orbit, densify=True,
                                on_step=lambda step, info: progress.update(task, completed=step))
