"""`radfield demo-scene`: a tiny synthetic scene with exact ground truth (the scenes: radfield.demo,
one registry; this module parses the options and prints what was written)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield import demo
from radfield.cli.common import Force, Quiet, check_options, check_output
from radfield.errors import RadfieldError
from radfield.util.ranges import AT_LEAST_0, AT_LEAST_1, Range

# each family's own options (radfield.demo.Family.options), as the flags a user types
FLAGS = {"deform": "--deform", "workers": "--workers", "times": "--times", "held_out_times": "--held-out-times",
         "lights": "--lights"}


def demo_scene(
    name: Annotated[str, typer.Argument(metavar="NAME", help="The scene: " + ", ".join(demo.names()) + " (each described below).")],
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
    check_options({"--train-views": (train_views, AT_LEAST_1), "--test-views": (test_views, AT_LEAST_1),
                   "--size": (size, Range(8)), "--seed": (seed, AT_LEAST_0), "--times": (times, AT_LEAST_1),
                   "--lights": (lights, AT_LEAST_1), "--workers": (workers, AT_LEAST_1)})
    scene = demo.get(name)
    own = {"deform": deform, "workers": workers if workers != 1 else None, "times": times,
           "held_out_times": held_out_times or None, "lights": lights}
    for option, value in own.items():
        if value is not None and option not in scene.family.options:
            family = next(f for f in demo.FAMILIES if option in f.options)
            raise RadfieldError(f"demo-scene {name}: {FLAGS[option]} is for the {family.name} scenes "
                                f"({', '.join(demo.names(family))})")
    existing = _scene_in(output)
    if existing is not None and existing.get("name") != name:   # --force would mix two scenes' files
        raise RadfieldError(f"{output}: holds the {existing.get('name', 'unnamed')} demo scene, not {name}; "
                            f"write {name} to another folder")
    if exist_ok and existing is not None and existing.get("seed") == seed and \
            existing.get("deform", {}).get("name") == deform:
        typer.echo(f"{output} already holds the {name} scene")
        return
    check_output(output, force, folder=True)
    settings = dict(train_views=train_views, test_views=test_views, size=size, seed=seed, quiet=quiet,
                    **{option: value for option, value in own.items() if value is not None})
    if output.is_dir() and any(output.iterdir()):   # --force: the scene's files replace those of the same names
        from radfield.util.atomic import atomic_folder

        with atomic_folder(output, merge=True) as tmp:
            summary = scene.write(tmp, **settings)
        summary = summary.replace(str(tmp), str(output))
    else:
        summary = scene.write(output, **settings)
    typer.echo(summary)


demo_scene.__doc__ = """Write a tiny synthetic NeRF-synthetic scene with exact ground truth (and its mesh.ply, except
    for objects, smoke and moving).

    """ + "\n\n    ".join(f"{family.title}: " + "; ".join(f"{s.name} ({s.about})" for s in demo.SCENES.values()
                                                            if s.family == family) + "."
                           for family in demo.FAMILIES)


def _scene_in(folder: Path) -> dict | None:
    """The scene.json of the demo scene `folder` holds, if it holds one."""
    import json

    try:
        described = json.loads((folder / "scene.json").read_text())
    except (OSError, ValueError):
        return None
    return described if isinstance(described, dict) and "name" in described else None
