"""`radfield edit`: apply an edit spec (and/or transform flags) to a run or a model file and write
a new run directory (layout in radfield.edit.field). This module is the glue between run
directories (radfield.stages) and the edit library (radfield.edit), which knows no stage."""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from pathlib import Path
from typing import Annotated, Optional

import typer
import yaml

from radfield.util.atomic import atomic_folder, atomic_write_text
from radfield.errors import RadfieldError

EDIT_STAGE = "edit"  # = radfield.edit.field.EDIT_STAGE (not imported here: keeps `radfield --help` fast)

SOURCE_CAGE = ("tetra", "cage.npz")             # the tetra stage's cage of a reconstructed run
SOURCE_BINDINGS = (("bind", "model_binding.npz"),   # the bind stage's binding of the trained model
                   ("train", "model_binding.npz"))  # where runs made before the bind stage have it


def run_files(run: Path) -> tuple[Path, Path | None, Path | None]:
    """(model, cage or None, binding or None) of a run directory, edited or reconstructed."""
    from radfield.pipeline.info import model_path

    model = model_path(run)
    if not model.is_file():
        raise RadfieldError(f"{run}: run directory has no trained model yet ({model} is missing)")
    if model.parent.name == EDIT_STAGE:
        cage, binding = run / EDIT_STAGE / "cage.npz", run / EDIT_STAGE / "model_binding.npz"
    else:
        cage = run.joinpath(*SOURCE_CAGE)
        binding = next((run.joinpath(*b) for b in SOURCE_BINDINGS if run.joinpath(*b).is_file()), None)
    return model, cage if cage.is_file() else None, binding if binding is not None and binding.is_file() else None


def load_source(path: Path, cage: Path | None = None):
    """A run directory (its final model, cage and binding) or a model file (with an optional cage
    file) as a Field; also EditContext.load_operand for operations that take another field."""
    from radfield.edit.field import load_field
    from radfield.pipeline.runner import is_run_dir

    path = Path(path)
    if is_run_dir(path):
        model, run_cage, binding = run_files(path)
        return load_field(model, cage or run_cage, binding if cage is None else None)
    if path.is_dir():
        raise RadfieldError(f"{path}: not a radfield run directory")
    if not path.is_file():
        raise RadfieldError(f"{path}: no such model file or run directory")
    return load_field(path, cage)


def _vector(text: str | None, name: str) -> list[float] | None:
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise RadfieldError(f"--{name} takes three comma-separated numbers like 0,0,90, got {text!r}")
    return values


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def edit(
    source: Annotated[Path, typer.Argument(metavar="RUN_OR_MODEL", help="A run directory (reconstructed or edited) or a .safetensors model file.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="New run directory to create (must not exist).")],
    spec: Annotated[Optional[Path], typer.Option("--spec", "-s", help="YAML edit spec with a list 'operations:' (README, 'Editing').")] = None,
    rotate: Annotated[Optional[str], typer.Option(help="Rotate the whole field: rx,ry,rz degrees, R = Rz·Ry·Rx (applied after the spec).")] = None,
    translate: Annotated[Optional[str], typer.Option(help="Translate the whole field: tx,ty,tz (world units).")] = None,
    scale: Annotated[Optional[float], typer.Option(help="Scale the whole field uniformly by this factor (about --origin).")] = None,
    origin: Annotated[Optional[str], typer.Option(help="Centre of --rotate/--scale: x,y,z (default 0,0,0).")] = None,
    cage: Annotated[Optional[Path], typer.Option(help="Cage file (.npz/.vtk/.vtu/.msh) for a model file, or to replace a run's cage.")] = None,
    gradient: Annotated[str, typer.Option(help="Per-primitive map: centre (deformation gradient interpolated at the centre) or tet (its tet's map).")] = "centre",
    split: Annotated[float, typer.Option(help="Split primitives whose tets' maps vary by more than this (relative); 0 disables.")] = 0.5,
    preserve_opacity: Annotated[bool, typer.Option("--preserve-opacity", help="Measure optical depth in rest-space distance (stretching keeps opacity); adds the rest_metric tensor.")] = False,
    seed: Annotated[int, typer.Option(help="Seed for operations that sample or train.")] = 0,
    device: Annotated[str, typer.Option(help="cpu or cuda, for operations that render or train.")] = "cpu",
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress messages.")] = False,
):
    """Edit a field through its cage and write a new run directory.

    Applies the spec's operations in order (transform, deform, twist, bend, taper, ...), then the
    --rotate/--translate/--scale flags. The source is never modified; OUTPUT must not exist and is
    written to a temporary folder renamed at the end. `radfield render/eval/info OUTPUT` work on it."""
    from radfield.cli.common import resolve_device
    from radfield.edit.field import EDIT_SPEC, save_field
    from radfield.edit.spec import EditContext, apply_operations, parse_spec, read_spec
    from radfield.pipeline.info import run_dataset
    from radfield.pipeline.runner import CONFIG_FILE, RUN_MARKER, format_figures, is_run_dir, read_marker

    start = time.perf_counter()
    if output.exists():
        raise RadfieldError(f"{output}: already exists (radfield edit writes a new run directory)")
    resolve_device(device)
    operations = read_spec(spec) if spec is not None else []
    flags = {"rotate": _vector(rotate, "rotate"), "translate": _vector(translate, "translate"),
             "scale": scale, "origin": _vector(origin, "origin")}
    flags = {k: v for k, v in flags.items() if v is not None}
    if set(flags) - {"origin"}:
        operations += parse_spec({"operations": [{"transform": {"select": "all", **flags}}]}, "flags")
    elif not operations:
        raise RadfieldError("nothing to do: give --spec and/or --rotate/--translate/--scale")
    if split < 0:
        raise RadfieldError(f"--split must be >= 0, got {split}")
    log = (lambda message: None) if quiet else (lambda message: typer.echo(message, err=True))

    fld = load_source(source, cage)
    ctx = EditContext(base_dir=spec.parent if spec is not None else Path("."), load_operand=load_source,
                      device=device, seed=seed, log=log,
                      options={"gradient": gradient, "split": split or None, "preserve_opacity": preserve_opacity})
    edited = apply_operations(fld, operations, ctx)

    source_model = run_files(source)[0] if is_run_dir(source) else source
    marker = {"kind": "radfield-run", "input": None}
    if is_run_dir(source):
        marker.update(read_marker(source))
        dataset = run_dataset(source)
        marker["input"] = str(Path(dataset).resolve()) if dataset is not None else None
    marker.update({"created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "edited_from": str(Path(source).resolve())})
    figures = {"operations": len(operations), "primitives": len(edited.prims),
               "split": sum(int(n.get("split", 0)) for n in edited.notes)}
    with atomic_folder(output) as tmp:
        save_field(tmp / EDIT_STAGE, edited)
        atomic_write_text(tmp / EDIT_STAGE / EDIT_SPEC, yaml.safe_dump(
            {"operations": [{name: args} for name, args in operations]}, sort_keys=False))
        manifest = {"done": True, "applicable": True, "seconds": time.perf_counter() - start, "figures": figures,
                    "source": str(Path(source).resolve()), "source_model_sha256": _sha256(source_model),
                    "options": ctx.options, "notes": edited.notes}
        atomic_write_text(tmp / EDIT_STAGE / "manifest.json", json.dumps(manifest, indent=1) + "\n")
        if is_run_dir(source) and (source / CONFIG_FILE).is_file():
            shutil.copyfile(source / CONFIG_FILE, tmp / CONFIG_FILE)
        atomic_write_text(tmp / RUN_MARKER, json.dumps(marker, indent=2) + "\n")
    split_total = figures["split"]
    typer.echo(f"edited {len(fld.prims)} -> {len(edited.prims)} {edited.prims.kind} primitives with "
               f"{len(operations)} operation(s) ({split_total} split); wrote {output}")
    for note in edited.notes:  # what each operation did (kept, dropped, retrained, teacher PSNR, ...)
        figures = {k: v for k, v in note.items() if k != "operation" and isinstance(v, (int, float, str, bool))}
        typer.echo(f"  {note.get('operation', '?')}: {format_figures(figures)}")
