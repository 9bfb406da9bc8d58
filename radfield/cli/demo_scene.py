"""`radfield demo-scene`: a tiny synthetic scene with exact ground truth (radfield.datasets.synthetic;
the dynamic scenes, `smoke` and `moving`: radfield.datasets.timelapse; the one-light-at-a-time
scenes, `olat` and `olat-glossy`: radfield.datasets.olat)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield.cli.common import Force, Quiet, check_options, check_output
from radfield.datasets.timelapse import SCENES as _DYNAMIC  # D-NeRF layout: every camera at every time
from radfield.errors import RadfieldError
from radfield.util.ranges import AT_LEAST_0, AT_LEAST_1, Range


def demo_scene(
    name: Annotated[str, typer.Argument(metavar="NAME", help="The scene: blobs, thin, checker, objects, glossy, studio; dynamic: smoke, moving; one light at a time: olat, olat-glossy (each described below).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder to create (an existing non-empty one needs --force).")],
    train_views: Annotated[Optional[int], typer.Option(help="Training views (default: the scene's own, 40; glossy and studio 100; smoke and moving 36 cameras; olat and olat-glossy 40 cameras).")] = None,
    test_views: Annotated[Optional[int], typer.Option(help="Held-out test views (default: the scene's own, 8; glossy and studio 20; smoke and moving 4 cameras; olat and olat-glossy 8 cameras).")] = None,
    size: Annotated[int, typer.Option(help="Image width and height in pixels.")] = 64,
    seed: Annotated[int, typer.Option(help="Turns the camera spiral.")] = 0,
    times: Annotated[Optional[int], typer.Option(help="smoke and moving only: the moments each camera photographs, k/(N-1) for k = 0..N-1 (default 24).")] = None,
    held_out_times: Annotated[bool, typer.Option("--held-out-times", help="smoke and moving only: the test cameras photograph the moments between the training times, (k+1/2)/(N-1), so no test time is a training time.")] = False,
    lights: Annotated[Optional[int], typer.Option(help="olat and olat-glossy only: the point lights each camera photographs the object under, every one at a new position (default 5).")] = None,
    workers: Annotated[int, typer.Option(help="Views rendered at once, in worker processes (the static scenes; the images are the same whatever the number).")] = 1,
    exist_ok: Annotated[bool, typer.Option("--exist-ok", help="Do nothing if OUTPUT already holds this scene (same name, seed and deformation).")] = False,
    deform: Annotated[Optional[str], typer.Option(help="Render the scene's shapes deformed by a smooth map, through the same cameras as the undeformed scene: twist (45 degrees per unit about z), bend (30 degrees per unit about y, along z) or squash (the affine map x' = A x, scales 1.2/0.9/0.8 with shears). Writes the map as an edit spec, OUTPUT/deform.yaml: the ground truth of `radfield edit RUN --spec OUTPUT/deform.yaml`.")] = None,
    force: Force = False,
    quiet: Quiet = False,
):
    """Write a tiny synthetic NeRF-synthetic scene with exact ground truth (and its mesh.ply, except
    for objects, smoke and moving).

    Static scenes (40 + 8 views): blobs (easy), thin (sub-pixel rods), checker (high-frequency
    texture), objects (separate objects, a torus, thin rods; no mesh.ply, so the envelope is the
    visual hull); glossy (glossy and matte objects with moving highlights) and studio (glossy's
    objects rendered like a path tracer: soft shadows, moderate highlights), 100 + 20 views.

    Dynamic scenes (a D-NeRF dataset, 36 + 4 cameras, each at --times moments): smoke (coloured
    puffs that move, grow and turn), moving (the objects scene's shapes moving and turning).

    One light at a time (40 + 8 cameras, each under --lights point lights, light_position per
    frame): olat (studio's objects), olat-glossy (glossy's: sharp highlights that move with the
    light, a pillar whose shadow sweeps the matte slab)."""
    import json

    from radfield.datasets.olat import SCENES as _OLAT  # one light at a time (imports numpy: not at start-up)

    check_options({"--train-views": (train_views, AT_LEAST_1), "--test-views": (test_views, AT_LEAST_1),
                   "--size": (size, Range(8)), "--seed": (seed, AT_LEAST_0), "--times": (times, AT_LEAST_1),
                   "--lights": (lights, AT_LEAST_1), "--workers": (workers, AT_LEAST_1)})
    if (name in _DYNAMIC or name in _OLAT) and deform is not None:
        raise RadfieldError(f"demo-scene {name}: --deform is for the static scenes")
    if name not in _DYNAMIC and times is not None:
        raise RadfieldError(f"demo-scene {name}: --times is for the dynamic scenes ({', '.join(_DYNAMIC)})")
    if name not in _DYNAMIC and held_out_times:
        raise RadfieldError(f"demo-scene {name}: --held-out-times is for the dynamic scenes ({', '.join(_DYNAMIC)})")
    if workers != 1 and (name in _DYNAMIC or name in _OLAT):
        raise RadfieldError(f"demo-scene {name}: --workers is for the static scenes")
    if name not in _OLAT and lights is not None:
        raise RadfieldError(f"demo-scene {name}: --lights is for the one-light-at-a-time scenes ({', '.join(_OLAT)})")
    if name not in _DYNAMIC and name not in _OLAT:
        from radfield.datasets.synthetic import SCENES

        if name not in SCENES:
            raise RadfieldError(f"unknown demo scene {name!r} (available: {', '.join([*SCENES, *_DYNAMIC, *_OLAT])})")
    existing = _scene_in(output)
    if existing is not None and existing.get("name") != name:   # --force would mix two scenes' files
        raise RadfieldError(f"{output}: holds the {existing.get('name', 'unnamed')} demo scene, not {name}; "
                            f"write {name} to another folder")
    if exist_ok and existing is not None and existing.get("seed") == seed and \
            existing.get("deform", {}).get("name") == deform:
        typer.echo(f"{output} already holds the {name} scene")
        return
    check_output(output, force, folder=True)

    def generate(folder: Path) -> None:
        if name in _DYNAMIC:
            _generate_dynamic(name, folder, train_views, test_views, times, size, seed, quiet, held_out_times)
        elif name in _OLAT:
            _generate_olat(name, folder, train_views, test_views, lights, size, seed, quiet)
        else:
            from radfield.datasets.synthetic import generate_scene

            generate_scene(name, folder, n_train=train_views, n_test=test_views, size=size, seed=seed, deform=deform,
                           workers=workers)

    if output.is_dir() and any(output.iterdir()):   # --force: the scene's files replace those of the same names
        from radfield.util.atomic import atomic_folder

        with atomic_folder(output, merge=True) as tmp:
            generate(tmp)
    else:
        generate(output)
    frames = {split: json.loads((output / f"transforms_{split}.json").read_text())["frames"] for split in ("train", "test")}
    if name in _DYNAMIC:
        moments = {split: len({frame["time"] for frame in frames[split]}) for split in frames}
        cameras = {split: len(frames[split]) // moments[split] for split in frames}
        between = f" (test at the {moments['test']} times between)" if held_out_times else ""
        typer.echo(f"wrote {name}: {cameras['train']} train + {cameras['test']} test cameras at {moments['train']} "
                   f"times{between} "
                   f"({len(frames['train'])} + {len(frames['test'])} frames) of {size}x{size} to {output}")
        return
    if name in _OLAT:
        per_camera = len({f["file_path"].rsplit("_l", 1)[1] for f in frames["train"]})
        typer.echo(f"wrote {name}: {len(frames['train']) // per_camera} train + {len(frames['test']) // per_camera} test "
                   f"cameras under {per_camera} point lights each, every frame its own light "
                   f"({len(frames['train'])} + {len(frames['test'])} frames) of {size}x{size} to {output}")
        return
    what = name if deform is None else f"{name} deformed by {deform} (edit spec: {output / 'deform.yaml'})"
    typer.echo(f"wrote {what}: {len(frames['train'])} train + {len(frames['test'])} test views of {size}x{size} to {output}")


def _scene_in(folder: Path) -> dict | None:
    """The scene.json of the demo scene `folder` holds, if it holds one."""
    import json

    try:
        described = json.loads((folder / "scene.json").read_text())
    except (OSError, ValueError):
        return None
    return described if isinstance(described, dict) and "name" in described else None


def _generate_dynamic(name: str, folder: Path, train_views, test_views, times, size: int, seed: int,
                      quiet: bool, held_out_times: bool = False) -> None:
    from radfield.datasets import timelapse
    from radfield.util.progress import progress_bar

    n_train = timelapse.TRAIN_VIEWS if train_views is None else train_views
    n_test = timelapse.TEST_VIEWS if test_views is None else test_views
    times = timelapse.TIMES if times is None else times
    with progress_bar(quiet) as progress:
        test_times = times - 1 if held_out_times else times
        task = progress.add_task(f"rendering {name}", total=max(0, n_train * times + n_test * test_times))
        timelapse.generate_dynamic(name, folder, n_train, n_test, times, size, seed,
                                   progress=lambda done: progress.advance(task, done), held_out_times=held_out_times)


def _generate_olat(name: str, folder: Path, train_views, test_views, lights, size: int, seed: int, quiet: bool) -> None:
    from radfield.datasets import olat
    from radfield.util.progress import progress_bar

    n_train = olat.TRAIN_VIEWS if train_views is None else train_views
    n_test = olat.TEST_VIEWS if test_views is None else test_views
    lights = olat.LIGHTS if lights is None else lights
    with progress_bar(quiet) as progress:
        task = progress.add_task(f"rendering {name}", total=max(0, (n_train + n_test) * lights))
        olat.generate_olat(folder, n_train, n_test, lights, size, seed,
                           progress=lambda done: progress.advance(task, done), name=name)
