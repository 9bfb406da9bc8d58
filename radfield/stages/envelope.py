"""Stage "envelope": `envelope.ply`, the closed coarse surface around the object that the cage fills
and the initial primitives are sampled in (radfield.core.geometry.envelope builds it), and `envelope.png`,
the envelope over the first training view, for a user to check.

Built from, by `envelope.source`: `points` (the SfM points of points.npz), `mesh` (the dataset's
mesh.ply), `hull` (the alpha masks of the training images), `triangulate` (the triangulate stage's
points: features matched across the posed training images of a dataset without points), `auto`
(the first of these the dataset has) or `none` (no envelope and no cage, on purpose: this stage and
tetra are not applicable). When `auto` ends at `triangulate` and the triangulate stage made no
points (its reason says why), the run has no envelope either.

A dynamic scene (views that carry a time) must be enclosed at every moment, so that the cage
edits every moment alike: its visual hull is the union of the per-moment hulls (each carved by
that moment's training views only: views of other moments would carve away what moved) when
every moment has at least MIN_VIEWS_PER_TIME views (the paper's 40-camera rigs, `demo-scene
smoke`), else (D-NeRF's monocular captures, one view a moment) the box about the cameras' focus.
A fallback (convex hull, box) is recorded in the figures and printed as one warning line.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

from radfield.core.geometry.envelope import (CARVING_PASSES, build_envelope, choose_source, focus_box, overlay_picture,
                                             visual_hull, write_envelope)
from radfield.errors import RadfieldError
from radfield.datasets.scene import POINTS, SCENE, load_scene
from radfield.pipeline.runner import Context, NotApplicable, Stage
from radfield.stages.triangulate import TRIANGULATED
from radfield.util.progress import progress_bar
from radfield import run as layout

ENVELOPE = layout.ENVELOPE_FILE
OVERLAY = "envelope.png"
# a moment's hull needs silhouettes from several sides: fewer views per moment than this, and a
# dynamic scene's envelope is the box about the cameras' focus
MIN_VIEWS_PER_TIME = 3


def run(ctx: Context) -> dict[str, Any]:
    cfg = ctx.config["envelope"]
    if cfg["source"] == "none":
        raise NotApplicable("envelope.source is none: no envelope and no cage, on purpose")
    scene = load_scene(ctx.inputs[SCENE])
    with np.load(ctx.inputs[POINTS]) as stored:
        points = {name: stored[name] for name in stored.files}
    train = scene.dataset("train")
    masked = train.load_image(0)[1] is not None  # the first image tells: datasets are RGB or RGBA throughout
    source = choose_source(cfg["source"], len(points["xyz"]) > 0, len(points["mesh_vertices"]) > 0, masked)
    if source == "triangulate":
        if ctx.inputs[TRIANGULATED] is None:
            why = "no triangulated points (see the triangulate stage)"
            raise NotApplicable(why) if cfg["source"] == "auto" else RadfieldError(
                f"config key envelope.source is triangulate but there are {why}")
        with np.load(ctx.inputs[TRIANGULATED]) as triangulated:
            points["xyz"] = triangulated["xyz"]
    if source in ("points", "triangulate"):
        v, f, figures = build_envelope(points["xyz"], cfg)
    elif source == "mesh":  # a mesh.ply without faces is a point cloud
        mesh = points["mesh_vertices"]
        v, f, figures = build_envelope((mesh, points["mesh_faces"]) if len(points["mesh_faces"]) else mesh, cfg)
    else:
        v, f, figures = hull_of_every_moment(train, cfg, ctx.quiet)
    write_envelope(ctx.outputs[ENVELOPE], v, f)
    overlay_picture(v, f, train.cameras[0], train.load_image(0)[0].numpy(), ctx.outputs[OVERLAY])
    ctx.log(f"{figures['faces']} faces from the {source} ({figures['method']}), margin {figures['margin']:.3g}")
    if figures["fallback"]:
        print(f"radfield: warning: envelope: fell back to the {figures['fallback']} ({figures['fallback_reason']})",
              file=sys.stderr, flush=True)
    return {"source": source, **figures}


def hull_of_every_moment(train, cfg: dict[str, Any], quiet: bool = True):
    """The visual hull of the training masks; for a dynamic scene the union of its moments' hulls,
    or the box about the cameras' focus when a moment has too few views (module docstring). Shows
    the loading and the carving as progress (unless `quiet`): 864 frames of a dynamic scene take
    a minute or two."""
    moments: dict[float, list[int]] = {}
    for k, camera in enumerate(train.cameras):
        if "time" in camera.conditions:   # the object moves: a hull per moment (the one time-aware stage)
            moments.setdefault(camera.conditions["time"], []).append(k)
    fewest = min((len(group) for group in moments.values()), default=0)
    if moments and fewest < MIN_VIEWS_PER_TIME:
        v, f, figures = focus_box(train.cameras, f"a dynamic scene with {fewest} training view(s) at some moment, "
                                                 f"too few for per-moment hulls (at least {MIN_VIEWS_PER_TIME})")
        return v, f, {**figures, "moments": len(moments)}
    groups = [moments[t] for t in sorted(moments)] or None
    with progress_bar(quiet) as progress:   # a dynamic scene's hull: one carving a moment and pass
        task = progress.add_task(f"loading {len(train)} training masks", total=len(train))
        masks = []
        for k, camera in enumerate(train.cameras):
            mask = train.load_image(k)[1]   # a view without alpha counts as all foreground
            masks.append(mask.numpy() if mask is not None else np.ones((camera.height, camera.width), np.float32))
            progress.advance(task)
        what = f"{len(groups)} moments' hulls" if groups else "the visual hull"
        task = progress.add_task(f"carving {what}", total=CARVING_PASSES * len(groups or [0]))
        v, f, figures = visual_hull(train.cameras, masks, cfg, groups=groups, on_carved=lambda: progress.advance(task))
    return v, f, {**figures, **({"moments": len(moments)} if moments else {})}


STAGE = Stage("envelope", run, config_keys=("envelope",), inputs=(SCENE, POINTS, TRIANGULATED),
              outputs=(ENVELOPE, OVERLAY), version=2)
