"""The cap of a cut face: thin opaque disc primitives seeded on the part of the cut surface that
lies inside the original object, so that the retrained cut face is closed, not hollow."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from radfield.core.geometry.camera_path import fibonacci_directions
from radfield.core.geometry.rotations import rotmat_to_quat
from radfield.core.kinds import NeuralPrimitives
from radfield.core.splat.sh import rgb_to_sh_dc, sh_to_color
from radfield.edit import retrain
from radfield.edit.boolean.shapes import Shape
from radfield.edit.boolean.surface import cut_surface
from radfield.edit.field import Field
from radfield.edit.recolor import peak_density


def cut_caps(original: NeuralPrimitives, straddlers: NeuralPrimitives, shape: Shape | None, other: Field | None,
             epsilon: float, op: str, seed: int) -> NeuralPrimitives:
    """Cap primitives for a cut (difference or intersection) of `original` through the straddling
    primitives: the operand's boundary sampled over their bounds (spacing their median radius)
    where it lies inside the object, the discs facing the kept side."""
    reach = straddlers.scales.detach().amax(-1)
    lo = (straddlers.means.detach() - reach[:, None]).amin(0).double().numpy()
    hi = (straddlers.means.detach() + reach[:, None]).amax(0).double().numpy()
    spacing = float(reach.median())
    pts, outward = cut_surface(shape, other, epsilon, lo, hi, spacing, seed)
    inward = op == "intersection"                                  # the kept side is the operand's inside
    return cap_primitives(original, pts, -outward if inward else outward, spacing, seed=seed)


def cap_primitives(original: NeuralPrimitives, pts: np.ndarray, normal: np.ndarray, spacing: float,
                   seed: int = 0) -> NeuralPrimitives:
    """Thin opaque discs at the cut-surface points `pts` (n, 3) that lie inside the original object,
    facing `normal` (n, 3), the unit normals into the kept region, coloured like the nearest
    original primitives."""
    empty = original.select(torch.zeros(0, dtype=torch.int64))
    if len(pts) == 0:
        return empty
    dirs = fibonacci_directions(14)
    occ = retrain.opacity_from(original, np.repeat(pts, 14, 0), np.tile(dirs, (len(pts), 1))).reshape(len(pts), 14)
    solid = (occ > 0.5).sum(1) >= 12
    pts, normal = pts[solid], normal[solid]
    if len(pts) == 0:
        return empty
    radius, thick = 0.8 * spacing, 0.25 * spacing
    # rotation taking z to the normal
    z = torch.as_tensor(normal)
    helper = torch.where((z[:, :1].abs() < 0.9), torch.tensor([[1.0, 0, 0]], dtype=torch.float64), torch.tensor([[0, 1.0, 0]], dtype=torch.float64))
    x = torch.nn.functional.normalize(torch.linalg.cross(helper, z), dim=-1)
    y = torch.linalg.cross(z, x)
    rot = torch.stack([x, y, z], -1)
    means = torch.as_tensor(pts + thick * normal)
    # optical depth across the disc at normal incidence: b2 · 2·thick / radius = 3 (α ≈ 0.95; the
    # same through the centre of a windowed disc, whose gain 1.5 keeps the central chord's depth)
    b2 = 3.0 * radius / (2 * thick)
    # colour: per-channel median over the 4 densest of the 16 nearest original primitives (robust
    # to the faint dark floaters a reconstruction keeps inside objects)
    k = min(16, len(original))
    _, near = cKDTree(original.means.detach().cpu().double().numpy()).query(pts, k=k)
    near = torch.as_tensor(near.reshape(len(pts), k))
    densest = torch.argsort(peak_density(original)[near], dim=1, descending=True)[:, :4]
    near, k = torch.gather(near, 1, densest), densest.shape[1]
    view = torch.nn.functional.normalize(-torch.as_tensor(normal), dim=-1)
    colours = sh_to_color(original.sh[near.reshape(-1)].detach().double(), view.repeat_interleave(k, 0), 0)
    colour = colours.reshape(len(pts), k, 3).median(1).values
    g = torch.Generator().manual_seed(seed)
    n, hidden = len(pts), original.hidden
    sh = torch.zeros(n, original.sh.shape[1], 3, dtype=torch.float64)
    sh[:, 0] = rgb_to_sh_dc(colour)
    dtype = original.means.dtype
    return NeuralPrimitives(
        means=means, log_scales=torch.log(torch.tensor([radius, radius, thick], dtype=torch.float64)).expand(n, 3).clone(),
        quats=rotmat_to_quat(rot), sh=sh,
        w1=(torch.rand(n, hidden, 3, generator=g, dtype=torch.float64) * 2 - 1) / 3,
        b1=(torch.rand(n, hidden, generator=g, dtype=torch.float64) * 2 - 1) / 3,
        w2=torch.zeros(n, hidden, dtype=torch.float64), b2=torch.full((n,), b2, dtype=torch.float64),
        omega0=original.omega0, supersample=original.supersample, window=original.window,
    ).to(dtype=dtype)
