"""The editable field: primitives, their cage and their binding, and how an edited field is stored.

`save_field` writes a field into a folder (an edited run keeps it in RUN/edit/; the run directory's
layout is radfield/run.py's, the edited run's other files radfield/edit/source.py's):

    model.safetensors   the edited model, a plain model file (world frame)
    cage.npz, cage.vtk  the cage in its edited pose (same topology as the source's)
    model_binding.npz   tet (P,) and bary (P, 4) of every primitive in that cage

Every coordinate is in the dataset's world frame, as models and cages are on disk.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from radfield.util.atomic import atomic_write
from radfield.core.geometry.cage import bind_to_cage, read_cage, write_cage
from radfield.model_file import save_model
from radfield.model_formats import load
from radfield.core.kinds import Primitives
from radfield import run as layout

EDIT_MODEL = layout.MODEL_FILE      # Run.model finds it in RUN/edit/
EDIT_BINDING = layout.BINDING_FILE


@dataclass
class Field:
    """A field being edited. `prims` in the world frame (CPU tensors); `cage_vertices` (V, 3) and
    `cage_tets` (T, 4) the cage in its current pose (None when the run has none); `tet` (P,) and
    `bary` (P, 4) bind each primitive's centre to a tet of the current cage (tet -1: unbound);
    `rest_vertices` (V, 3) the cage as it was when the binding was made (deformations map
    rest -> current). `notes` collects the figures each operation reports (for the manifest)."""

    prims: Primitives
    cage_vertices: np.ndarray | None = None
    cage_tets: np.ndarray | None = None
    tet: np.ndarray | None = None
    bary: np.ndarray | None = None
    notes: list[dict] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.tet is None:
            self.tet = np.full(len(self.prims), -1, np.int64)
            self.bary = np.zeros((len(self.prims), 4))

    @property
    def has_cage(self) -> bool:
        return self.cage_vertices is not None and self.cage_tets is not None

    def with_prims(self, prims: Primitives, tet=None, bary=None) -> "Field":
        """A copy with other primitives (and their binding; rebound to the cage when omitted)."""
        out = replace(self, prims=prims, tet=tet, bary=bary, notes=list(self.notes))
        if tet is None:
            out.rebind()
        return out

    def rebind(self) -> None:
        """Bind every primitive's centre to the current cage (nearest tet when outside)."""
        if not self.has_cage:
            self.tet, self.bary = np.full(len(self.prims), -1, np.int64), np.zeros((len(self.prims), 4))
            return
        means = self.prims.means.detach().cpu().double().numpy()
        self.tet, self.bary = bind_to_cage(means, (self.cage_vertices, self.cage_tets))


def load_field(model: str | Path, cage: str | Path | None = None, binding: str | Path | None = None) -> Field:
    """A Field from a model file and optionally its cage (any format read_cage reads) and binding
    (`binding.npz`; recomputed from the cage when absent or of another length)."""
    prims = load(model)
    if cage is None:
        return Field(prims)
    vertices, tets = read_cage(cage)
    tet = bary = None
    if binding is not None and Path(binding).is_file():
        with np.load(binding, allow_pickle=False) as data:
            if len(data["tet"]) == len(prims):
                tet, bary = data["tet"].astype(np.int64), data["bary"].astype(np.float64)
    out = Field(prims, vertices, tets, tet, bary)
    if tet is None:
        out.rebind()
    return out


def save_field(out_dir: str | Path, fld: Field, extra: dict | None = None) -> list[Path]:
    """Write the model, the cage (if any) and the binding into `out_dir` (atomically, file by file)."""
    out_dir = Path(out_dir)
    save_model(out_dir / EDIT_MODEL, fld.prims, extra=extra)
    written = [out_dir / EDIT_MODEL]
    if fld.has_cage:
        written += write_cage(out_dir, fld.cage_vertices, fld.cage_tets)
    atomic_write(out_dir / EDIT_BINDING, lambda tmp: np.savez(tmp, tet=fld.tet, bary=fld.bary))
    return written + [out_dir / EDIT_BINDING]


def box_cage(lo, hi, n: int | tuple[int, int, int] = 2) -> tuple[np.ndarray, np.ndarray]:
    """A regular tet cage of the box [lo, hi]: n³ cells of 6 tets each (Kuhn split, positive
    orientation). For tests, and for fields whose run has no cage."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    n = np.broadcast_to(np.asarray(n), (3,)).astype(int)
    axes = [np.linspace(lo[i], hi[i], n[i] + 1) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    index = np.arange(grid.shape[0]).reshape(*(n + 1))
    cube = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]])
    kuhn = [[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]]
    cells = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1).reshape(-1, 3)
    corners = index[tuple((cells[:, None, :] + cube[None]).transpose(2, 0, 1))]   # (C, 8)
    tets = corners[:, kuhn].reshape(-1, 4)
    c = grid[tets]
    flip = np.linalg.det(c[:, 1:] - c[:, :1]) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return grid, tets
