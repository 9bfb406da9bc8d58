"""`radfield demo-scene`: a tiny synthetic scene with exact ground truth (radfield.datasets.synthetic)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield.cli.common import Force, check_output


def demo_scene(
    name: Annotated[str, typer.Argument(help="blobs (easy), thin (sub-pixel rods), checker (high-frequency texture), objects (separate objects, a torus, thin rods; no mesh.ply, so the envelope is the visual hull), glossy (glossy and matte objects with moving specular highlights; 100 + 20 views) or studio (glossy's objects rendered like a path tracer: 8x8 jittered rays per pixel, soft shadows, moderate highlights; 100 + 20 views).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder to create (an existing non-empty one needs --force).")],
    train_views: Annotated[Optional[int], typer.Option(help="Training views (default: the scene's own, 40; glossy and studio 100).")] = None,
    test_views: Annotated[Optional[int], typer.Option(help="Held-out test views (default: the scene's own, 8; glossy and studio 20).")] = None,
    size: Annotated[int, typer.Option(help="Image width and height in pixels.")] = 64,
    seed: Annotated[int, typer.Option(help="Turns the camera spiral.")] = 0,
    exist_ok: Annotated[bool, typer.Option("--exist-ok", help="Do nothing if OUTPUT already holds this scene (same name, seed and deformation).")] = False,
    deform: Annotated[Optional[str], typer.Option(help="Render the scene's shapes deformed by a smooth map, through the same cameras as the undeformed scene: twist (45 degrees per unit about z), bend (30 degrees per unit about y, along z) or squash (the affine map x' = A x, scales 1.2/0.9/0.8 with shears). Writes the map as an edit spec, OUTPUT/deform.yaml: the ground truth of `radfield edit RUN --spec OUTPUT/deform.yaml`.")] = None,
    force: Force = False,
):
    """Write a tiny synthetic NeRF-synthetic scene with exact ground truth (and its mesh.ply, except for objects)."""
    import json

    from radfield.datasets.synthetic import generate_scene

    if exist_ok and (output / "scene.json").is_file():
        existing = json.loads((output / "scene.json").read_text())
        if existing.get("name") == name and existing.get("seed") == seed and existing.get("deform", {}).get("name") == deform:
            typer.echo(f"{output} already holds the {name} scene")
            return
    check_output(output, force, folder=True)
    if output.is_dir() and any(output.iterdir()):   # --force: the scene's files replace those of the same names
        from radfield.util.atomic import atomic_folder

        with atomic_folder(output, merge=True) as tmp:
            generate_scene(name, tmp, n_train=train_views, n_test=test_views, size=size, seed=seed, deform=deform)
    else:
        generate_scene(name, output, n_train=train_views, n_test=test_views, size=size, seed=seed, deform=deform)
    counts = {split: len(json.loads((output / f"transforms_{split}.json").read_text())["frames"]) for split in ("train", "test")}
    what = name if deform is None else f"{name} deformed by {deform} (edit spec: {output / 'deform.yaml'})"
    typer.echo(f"wrote {what}: {counts['train']} train + {counts['test']} test views of {size}x{size} to {output}")
