"""`radfield edit`: apply an edit spec (and/or transform flags) to a run or a model file and write a
new run directory (radfield.edit.source writes it; the operations are radfield.edit.spec's)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from radfield.cli.common import Force, check_options, check_output, resolve_device
from radfield.errors import RadfieldError
from radfield.util.ranges import AT_LEAST_0, POSITIVE
from radfield.util.numbers import three_numbers


def _vector(text: str | None, name: str) -> list[float] | None:
    if text is None:
        return None
    values = three_numbers(text)
    if values is None:
        raise RadfieldError(f"--{name} takes three comma-separated numbers like 0,0,90, got {text!r}")
    return list(values)


def edit(
    source: Annotated[Path, typer.Argument(metavar="RUN_OR_MODEL", help="A run directory (reconstructed or edited) or a model file: radfield's .safetensors, or any format `radfield import` reads (a 3DGS PLY, .spz, .splat, .glb, a Splat the Net PLY).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="New run directory to create (an existing non-empty folder needs --force; never an existing run).")],
    spec: Annotated[Optional[Path], typer.Option("--spec", "-s", help="YAML edit spec with a list 'operations:' (docs/usage.md, 'Editing').")] = None,
    rotate: Annotated[Optional[str], typer.Option(help="Rotate the whole field: rx,ry,rz degrees, R = Rz·Ry·Rx (applied after the spec).")] = None,
    translate: Annotated[Optional[str], typer.Option(help="Translate the whole field: tx,ty,tz (world units).")] = None,
    scale: Annotated[Optional[float], typer.Option(help="Scale the whole field uniformly by this factor (about --origin).")] = None,
    origin: Annotated[Optional[str], typer.Option(help="Centre of --rotate/--scale: x,y,z (default 0,0,0).")] = None,
    cage: Annotated[Optional[Path], typer.Option(help="Cage file (.npz/.vtk/.vtu/.msh) for a model file, or to replace a run's cage.")] = None,
    gradient: Annotated[Optional[str], typer.Option(help="Per-primitive map: map (the operation's closed-form map and Jacobian at each centre), smooth (higher-order cage interpolation), centre or tet (docs/usage.md 'How primitives follow the cage').", show_default="map for transform/twist/bend/taper, smooth for a cage file")] = None,
    split_threshold: Annotated[float, typer.Option("--split-threshold", help="Split primitives whose tets' maps vary by more than this (relative); 0 disables.")] = 0.5,
    # `--split` is a dataset split in render/eval/animate; edit's old name for the threshold stays
    # one release as a hidden alias with a deprecation note (docs/usage.md, 'Editing')
    split_old: Annotated[Optional[float], typer.Option("--split", hidden=True)] = None,
    preserve_opacity: Annotated[Optional[bool], typer.Option("--preserve-opacity/--no-preserve-opacity", show_default=False, help="Measure optical depth in rest-space distance, so stretching keeps opacity (adds the rest_metric tensor). Default: on exactly where the edit maps a primitive by more than a similarity (rotation, uniform scale, translation).")] = None,
    seed: Annotated[int, typer.Option(help="Seed for operations that sample or train.")] = 0,
    device: Annotated[str, typer.Option(help="cpu or cuda, for operations that render or train.")] = "cpu",
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress messages.")] = False,
    force: Force = False,
):
    """Edit a field through its cage and write a new run directory.

    Applies the spec's operations in order (transform, deform, twist, bend, taper, ...), then the
    --rotate/--translate/--scale flags. The source is never modified; OUTPUT is written to a temporary
    folder renamed at the end (docs/usage.md, 'Outputs'). `radfield render/eval/info OUTPUT` work on it."""
    from radfield.edit.source import load_source, write_edited_run
    from radfield.edit.spec import EditContext, apply_operations, parse_spec, read_spec
    from radfield.pipeline.runner import format_figures

    start = time.perf_counter()
    check_options({"--scale": (scale, POSITIVE), "--split-threshold": (split_threshold, AT_LEAST_0),
                   "--split": (split_old, AT_LEAST_0), "--seed": (seed, AT_LEAST_0)})
    check_output(output, force, folder=True)
    resolve_device(device)
    operations = read_spec(spec) if spec is not None else []
    sources = [str(spec)] * len(operations)   # a bad value in the spec: its error names the file
    flags = {"rotate": _vector(rotate, "rotate"), "translate": _vector(translate, "translate"),
             "scale": scale, "origin": _vector(origin, "origin")}
    flags = {k: v for k, v in flags.items() if v is not None}
    if set(flags) - {"origin"}:
        operations += parse_spec({"operations": [{"transform": {"select": "all", **flags}}]}, "flags")
        sources.append("--rotate/--translate/--scale")
    elif not operations:
        raise RadfieldError("nothing to do: give --spec and/or --rotate/--translate/--scale")
    if split_old is not None:
        typer.echo("radfield: note: edit --split is deprecated and will be removed; use --split-threshold (same meaning)", err=True)
        split_threshold = split_old
    split = split_threshold
    log = (lambda message: None) if quiet else (lambda message: typer.echo(message, err=True))

    fld = load_source(source, cage)
    ctx = EditContext(base_dir=spec.parent if spec is not None else Path("."), load_operand=load_source,
                      device=device, seed=seed, log=log,
                      options={"gradient": gradient, "split": split or None, "preserve_opacity": preserve_opacity})
    edited = apply_operations(fld, operations, ctx, sources)
    figures = write_edited_run(output, source, edited, operations, ctx.options, start)
    split_total = figures["split"]
    typer.echo(f"edited {len(fld.prims)} -> {len(edited.prims)} {edited.prims.kind} primitives with "
               f"{len(operations)} operation(s) ({split_total} split); wrote {output}")
    for note in edited.notes:  # what each operation did (kept, dropped, retrained, teacher PSNR, ...)
        figures = {k: v for k, v in note.items() if k != "operation" and isinstance(v, (int, float, str, bool))}
        typer.echo(f"  {note.get('operation', '?')}: {format_figures(figures)}")
