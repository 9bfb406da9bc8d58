"""`radfield eval --compare RUN_A RUN_B ... -o DIR`: evaluate several runs (or model files) on the
same views and put them side by side.

DIR/report.md          one table: PSNR, SSIM, LPIPS, primitives, parameters, file size, FPS, train
                       time (from the run's train manifest), and the side-by-side grids
DIR/comparison.json    [{"label", "target", "train_seconds", "metrics": <metrics.json>}, ...]
DIR/grids/<view>.png   ground truth | render of each run, captioned
DIR/<label>/           each run's own evaluation (metrics.json, report.md, renders/, grids/)

The runs are evaluated one after another on this machine, so their FPS compare.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

from radfield.evaluation import report
from radfield.util.atomic import atomic_folder, atomic_write_text
from radfield.errors import RadfieldError
from radfield.datasets.images import read_image, write_image
from radfield.run import MODEL_STAGE, Run
from radfield.evaluation.evaluate import GRIDS, RENDERS, REPORT, eval_report, resolve_target

COMPARISON = "comparison.json"


def labels_for(targets: Sequence[Path]) -> list[str]:
    """Folder-safe, unique labels: the run's folder name (a model file's stem), numbered on clashes."""
    names = [Path(t).stem if Path(t).is_file() else Path(t).resolve().name for t in targets]
    out = []
    for i, name in enumerate(names):
        label = name if names.count(name) == 1 else f"{name}-{i + 1}"
        out.append(label if label not in (GRIDS, REPORT, COMPARISON) else f"{label}-run")
    return out


def compare(targets: Sequence[Path], out_dir: Path, *, dataset: Path | None, split: str,
            options: dict[str, Any] | None = None, device: str = "cpu", quiet: bool = True) -> list[dict[str, Any]]:
    """Evaluate every target on `split` into `out_dir` (layout in the module docstring)."""
    if len(targets) < 2:
        raise RadfieldError("--compare needs at least two runs or model files")
    if out_dir.exists() and not out_dir.is_dir():
        raise RadfieldError(f"{out_dir}: exists and is not a folder")
    resolved = [resolve_target(t, dataset, options) for t in targets]  # every mistake before any work
    views = [[v["name"] for v in scene.views(split)] for _, scene, _, _ in resolved]
    sizes = [(c.width, c.height) for _, scene, _, _ in resolved for c in scene.cameras(split)[:1]]
    for target, names, size in zip(targets, views, sizes):
        if names != views[0] or size != sizes[0]:
            raise RadfieldError(f"{target}: its {split} views ({len(names)} of {size[0]}×{size[1]}) are not those of "
                                f"{targets[0]} ({len(views[0])} of {sizes[0][0]}×{sizes[0][1]}); pass --dataset")
    labels = labels_for(targets)
    rows = []
    with atomic_folder(out_dir, merge=True) as tmp:
        for label, target, (_, _, run_dir, _) in zip(labels, targets, resolved):
            metrics = eval_report(target, dataset, split, tmp / label, options=options, device=device, quiet=quiet)
            rows.append({"label": label, "target": str(Path(target).resolve()), "metrics": metrics,
                         "train_seconds": _train_seconds(run_dir)})
        photos, _ = resolved[0][1].load_images(split)
        (tmp / GRIDS).mkdir()
        for i, name in enumerate(views[0]):
            renders = [read_image(tmp / label / RENDERS / f"{name}.png")[..., :3] for label in labels]
            write_image(tmp / GRIDS / f"{name}.png", report.side_by_side(photos[i].numpy(), renders, labels))
        atomic_write_text(tmp / COMPARISON, json.dumps(rows, indent=1) + "\n")
        atomic_write_text(tmp / REPORT, report.compare_markdown(rows, split=split, views=len(views[0]), grids_dir=GRIDS))
    return rows


def _train_seconds(run_dir: Path | None) -> float | None:
    if run_dir is None:
        return None
    return (Run(run_dir).manifest(MODEL_STAGE) or {}).get("seconds")
