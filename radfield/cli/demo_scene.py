"""`radfield demo-scene`: a tiny synthetic scene with exact ground truth (radfield.datasets.synthetic)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer


def demo_scene(
    name: Annotated[str, typer.Argument(help="blobs (easy), thin (sub-pixel rods), checker (high-frequency texture), objects (separate objects, a torus, thin rods; no mesh.ply, so the envelope is the visual hull), glossy (glossy and matte objects with moving specular highlights; 100 + 20 views) or studio (glossy's objects rendered like a path tracer: 8x8 jittered rays per pixel, soft shadows, moderate highlights; 100 + 20 views).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder to create (must not exist or be empty).")],
    train_views: Annotated[Optional[int], typer.Option(help="Training views (default: the scene's own, 40; glossy and studio 100).")] = None,
    test_views: Annotated[Optional[int], typer.Option(help="Held-out test views (default: the scene's own, 8; glossy and studio 20).")] = None,
    size: Annotated[int, typer.Option(help="Image width and height in pixels.")] = 64,
    seed: Annotated[int, typer.Option(help="Turns the camera spiral.")] = 0,
    exist_ok: Annotated[bool, typer.Option("--exist-ok", help="Do nothing if OUTPUT already holds this scene (same name and seed).")] = False,
):
    """Write a tiny synthetic NeRF-synthetic scene with exact ground truth (and its mesh.ply, except for objects)."""
    import json

    from radfield.datasets.synthetic import generate_scene

    if exist_ok and (output / "scene.json").is_file():
        existing = json.loads((output / "scene.json").read_text())
        if existing.get("name") == name and existing.get("seed") == seed:
            typer.echo(f"{output} already holds the {name} scene")
            return
    generate_scene(name, output, n_train=train_views, n_test=test_views, size=size, seed=seed)
    counts = {split: len(json.loads((output / f"transforms_{split}.json").read_text())["frames"]) for split in ("train", "test")}
    typer.echo(f"wrote {name}: {counts['train']} train + {counts['test']} test views of {size}x{size} to {output}")
