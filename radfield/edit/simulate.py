"""A small soft-body simulation on the cage (Neural Impostor §6.1: the cage is the simulation
mesh): gravity, a ground plane with friction, elastic tets. The result is a sequence of cage
poses that `radfield animate` renders.

Solver: XPBD (Macklin et al. 2016) with small steps (Macklin et al. 2019: many substeps, one
iteration each), the constraints of "A Constraint-based Formulation of Stable Neo-Hookean
Materials" (Macklin & Müller 2021) per tet: with F = D_s D_m⁻¹,
    C_D = ‖F‖_F − √3  (compliance 1/(μ V)),   C_H = det F − 1  (compliance 1/(λ V)),
both zero at rest; Lamé μ = E/(2(1+ν)), λ = Eν/((1+ν)(1−2ν)). Tets are projected together
(Gauss-Seidel over a colouring of the tets: a colour's tets share no vertex and are projected at
once, vectorised in numpy).
Collision: vertices below the ground plane (height h·n = ground along n = −g/|g|) are projected
onto it; their tangential motion in that substep is scaled by (1 − friction).

Substeps adapt: `substeps` is the least number per frame. XPBD is not bound by an explicit
integrator's CFL limit (it stays finite at any step), but with one Gauss-Seidel iteration per
substep a step too long for the material's stiffness and the impact leaves constraints so far from
solved that tets flip — the docs' settings at fps 12 (h = 1/240 s) inverted tets of the objects
scene's cage at frame 3, where h = 1/600 s does not. The CFL bound (smallest tet altitude over the
dilatational wave speed √((λ+2μ)/ρ): 1/2262 s there) is 4× more than that case needs, and a
softer case needs fewer, so no bound is guessed: a frame whose substeps would leave any tet
inverted or flat (volume <= 1e-9 of its rest volume, what `edit.affine` refuses to render) is
undone and re-run with twice the substeps, and later frames keep the larger count. A frame that
still inverts a tet at MAX_SUBSTEPS substeps is a one-line error (the material is too soft for its
load) before anything is rendered.

A CPU simulation library was considered first: warp-lang's `warp.sim` (FEM and XPBD soft bodies)
was deprecated and moved to NVIDIA Newton, a GPU-first robotics engine (a large dependency with
kernel compilation at first use on a 2-core machine); a cage of a few thousand tets needs none of
that, and this solver is short enough to test directly.

Spec (`radfield animate RUN --simulate sim.yaml`), every key optional:
    simulate: {gravity: [0, 0, -9.8], ground: -0.6, youngs_modulus: 1e6, poisson_ratio: 0.3,
               density: 1000, damping: 0.5, friction: 0.6, frames: 60, fps: 30, substeps: 20,
               initial_velocity: [0, 0, 0]}
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from radfield.core.geometry.cage import tet_volumes
from radfield.errors import RadfieldError
from radfield.edit.select import number, vector
from radfield.edit.spec import read_yaml

DEFAULTS = {"gravity": [0.0, 0.0, -9.8], "ground": None, "youngs_modulus": 1e6, "poisson_ratio": 0.3,
            "density": 1000.0, "damping": 0.5, "friction": 0.6, "frames": 60, "fps": 30.0, "substeps": 20,
            "initial_velocity": [0.0, 0.0, 0.0]}
MAX_SUBSTEPS = 5120          # per frame: 20 doubled 8 times; a frame needing more is refused
FLAT = 1e-9                  # a tet whose volume falls to FLAT × its rest volume counts as inverted


def parse_simulation(args: Mapping, where: str = "simulate") -> dict:
    """Checked simulation parameters (module docstring); `ground` None: 0.3 below the lowest vertex."""
    if not isinstance(args, Mapping):
        raise RadfieldError(f"{where}: expected a mapping of parameters, got {args!r}")
    unknown = sorted(set(args) - set(DEFAULTS))
    if unknown:
        raise RadfieldError(f"{where}: unknown parameters {unknown} (allowed: {', '.join(DEFAULTS)})")
    p = {**DEFAULTS, **args}
    out = {"gravity": vector(p, "gravity", where), "initial_velocity": vector(p, "initial_velocity", where),
           "ground": None if p["ground"] is None else number(p, "ground", where)}
    for key in ("youngs_modulus", "density", "fps"):
        out[key] = number(p, key, where, positive=True)
    for key in ("damping", "friction"):
        out[key] = number(p, key, where)
        if out[key] < 0:
            raise RadfieldError(f"{where}.{key}: must be >= 0, got {out[key]}")
    out["friction"] = min(out["friction"], 1.0)
    out["poisson_ratio"] = number(p, "poisson_ratio", where)
    if not 0.0 <= out["poisson_ratio"] < 0.5:
        raise RadfieldError(f"{where}.poisson_ratio: must be in [0, 0.5), got {out['poisson_ratio']}")
    for key in ("frames", "substeps"):
        if isinstance(p[key], bool) or not isinstance(p[key], int) or p[key] < 1:
            raise RadfieldError(f"{where}.{key}: expected a whole number >= 1, got {p[key]!r}")
        out[key] = p[key]
    if not np.linalg.norm(out["gravity"]) > 0:
        raise RadfieldError(f"{where}.gravity: must not be zero (it also defines 'up' for the ground)")
    return out


def read_simulation(path: str | Path) -> dict:
    """The `simulate:` mapping of a YAML file, checked."""
    data = read_yaml(path, "the simulation")
    if not isinstance(data, Mapping) or set(data) != {"simulate"}:
        raise RadfieldError(f"{path}: expected one top-level key 'simulate:' with the simulation's parameters")
    return parse_simulation(data["simulate"] or {}, f"{path}: simulate")


def colour_tets(tets: np.ndarray, n_vertices: int) -> np.ndarray:
    """Greedy colouring (T,) of the tets: two tets sharing a vertex never get the same colour."""
    colour = np.full(len(tets), -1)
    used: list[set[int]] = [set() for _ in range(n_vertices)]   # colours present at each vertex
    for i, tet in enumerate(tets.tolist()):
        taken = used[tet[0]] | used[tet[1]] | used[tet[2]] | used[tet[3]]
        c = 0
        while c in taken:
            c += 1
        colour[i] = c
        for v in tet:
            used[v].add(c)
    return colour


class SoftBody:
    """XPBD state of a tet mesh (module docstring). `step(dt)` advances by one frame."""

    def __init__(self, vertices: np.ndarray, tets: np.ndarray, params: dict):
        self.x = np.array(vertices, np.float64)
        self.tets = np.asarray(tets, np.int64)
        self.p = params
        self.substeps = params["substeps"]   # the count now in use (it only grows: module docstring)
        self.v = np.broadcast_to(params["initial_velocity"], self.x.shape).copy()
        rest = self.x[self.tets]
        dm = np.swapaxes(rest[:, 1:] - rest[:, :1], 1, 2)
        self.dm_inv = np.linalg.inv(dm)
        self.volume = np.abs(tet_volumes(self.x, self.tets))
        mass = np.zeros(len(self.x))
        np.add.at(mass, self.tets.ravel(), np.repeat(params["density"] * self.volume / 4, 4))
        self.w = 1.0 / np.maximum(mass, 1e-12)
        self.mass = mass
        colour = colour_tets(self.tets, len(self.x))
        self.colours = [(self.tets[colour == c], self.dm_inv[colour == c], self.volume[colour == c])
                        for c in range(colour.max() + 1)]
        e, nu = params["youngs_modulus"], params["poisson_ratio"]
        self.mu, self.lam = e / (2 * (1 + nu)), e * nu / ((1 + nu) * (1 - 2 * nu))
        g = params["gravity"]
        self.up = -g / np.linalg.norm(g)
        ground = params["ground"]
        self.ground = float((self.x @ self.up).min() - 0.3) if ground is None else float(ground)

    def deformation(self, x):
        c = x[self.tets]
        ds = np.swapaxes(c[:, 1:] - c[:, :1], 1, 2)
        return ds @ self.dm_inv

    def _project(self, x, h):
        """One Gauss-Seidel XPBD pass over both constraints of every tet, a colour at a time (tets
        of one colour share no vertex, so each colour is projected at once, vectorised)."""
        for tets, dm_inv, vol in self.colours:
            for which in ("deviatoric", "volume"):
                c4 = x[tets]                                              # (T, 4, 3)
                f = np.swapaxes(c4[:, 1:] - c4[:, :1], 1, 2) @ dm_inv
                if which == "deviatoric":
                    norm = np.sqrt((f**2).sum((1, 2)))
                    c, grad_f, compliance = norm - np.sqrt(3.0), f / norm[:, None, None], 1.0 / (self.mu * vol)
                else:
                    grad_f = np.stack([np.cross(f[:, :, 1], f[:, :, 2]), np.cross(f[:, :, 2], f[:, :, 0]),
                                       np.cross(f[:, :, 0], f[:, :, 1])], 2)    # d det F / dF
                    c, compliance = np.linalg.det(f) - 1.0, 1.0 / (self.lam * vol)
                g123 = grad_f @ np.swapaxes(dm_inv, 1, 2)                     # dC/dx_1..3 as columns
                grads = np.concatenate([-g123.sum(2, keepdims=True), g123], 2)  # (T, 3, 4)
                w = self.w[tets]
                denom = (w * (grads**2).sum(1)).sum(1) + compliance / (h * h)
                dlam = -c / np.maximum(denom, 1e-300)
                x[tets] += np.swapaxes(grads, 1, 2) * (w * dlam[:, None])[..., None]
        return x

    def substep(self, h: float):
        p = self.p
        prev = self.x.copy()
        v = self.v + h * p["gravity"]
        x = self.x + h * v
        x = self._project(x, h)
        # ground: project below-ground vertices onto the plane, with friction on their sliding
        height = x @ self.up
        below = height < self.ground
        if below.any():
            x[below] += (self.ground - height[below])[:, None] * self.up
            move = x[below] - prev[below]
            tangential = move - (move @ self.up)[:, None] * self.up
            x[below] -= p["friction"] * tangential
        self.v = (x - prev) / h * max(0.0, 1.0 - p["damping"] * h)
        self.x = x

    def inverted(self) -> bool:
        """Whether any tet is inverted or flat now (volume <= FLAT × its rest volume)."""
        return bool((tet_volumes(self.x, self.tets) <= FLAT * self.volume).any())

    def step(self, dt: float) -> bool:
        """Advance by dt in `self.substeps` substeps; a run of substeps that inverts a tet at any
        substep is undone and repeated with twice as many (up to MAX_SUBSTEPS). Returns whether
        the frame ended with no inverted tet."""
        start = self.x.copy(), self.v.copy()
        while True:
            n = self.substeps
            for _ in range(n):
                self.substep(dt / n)
                if self.inverted():
                    break
            else:
                return True
            if 2 * n > MAX_SUBSTEPS:
                return False
            self.x, self.v = start[0].copy(), start[1].copy()
            self.substeps = 2 * n

    def energy(self) -> dict:
        """Kinetic, gravitational (relative to the ground) and elastic energy (J)."""
        f = self.deformation(self.x)
        c_d = np.sqrt((f**2).sum((1, 2))) - np.sqrt(3.0)
        c_h = np.linalg.det(f) - 1.0
        kinetic = 0.5 * float((self.mass * (self.v**2).sum(1)).sum())
        potential = float((self.mass * (self.x @ self.up - self.ground)).sum() * np.linalg.norm(self.p["gravity"]))
        elastic = 0.5 * float((self.volume * (self.mu * c_d**2 + self.lam * c_h**2)).sum())
        return {"kinetic": kinetic, "potential": potential, "elastic": elastic, "total": kinetic + potential + elastic}


def simulate_cage(vertices: np.ndarray, tets: np.ndarray, params: dict,
                  log: Callable[[str], None] | None = None) -> tuple[list[np.ndarray], dict]:
    """Cage poses (frames of (V, 3), the first the rest pose) and figures: the ground, the
    lowest height reached, the energies at the start and the end, the largest energy seen."""
    body = SoftBody(vertices, tets, params)
    lowest = float((body.x @ body.up).min())
    if body.ground > lowest + 1e-9:
        # a body starting inside the ground is shot out of it (each substep's push becomes a velocity
        # of push/h) and its bottom tets flip, however many substeps: a mistake in the file, for this cage
        raise RadfieldError(f"simulate.ground: {body.ground:g} is above the cage's lowest point ({lowest:.4g} along "
                            f"-gravity): the body would start inside the ground (omit ground: 0.3 below that point)")
    if body.inverted():
        raise RadfieldError("simulate: the cage has flat or inverted tets at rest (volume <= 0); it cannot be simulated")
    # said before the work, not as its success: the frames are still to be simulated and rendered
    if log:
        log(f"simulating {params['frames']} frames at {params['fps']:g} fps (at least {params['substeps']} substeps a frame)...")
    poses, energies = [body.x.copy()], [body.energy()["total"]]
    for frame in range(1, params["frames"]):
        ok = body.step(1.0 / params["fps"])
        if not np.isfinite(body.x).all():
            raise RadfieldError(f"simulate: the simulation diverged at frame {frame} (raise substeps or lower youngs_modulus)")
        if not ok:
            raise RadfieldError(f"simulate: tets of the cage invert at frame {frame} even with {MAX_SUBSTEPS} substeps "
                                f"a frame: the material is too soft for its load (raise youngs_modulus or "
                                f"poisson_ratio, or lower density or gravity)")
        poses.append(body.x.copy())
        energies.append(body.energy()["total"])
    volumes = tet_volumes(body.x, body.tets)
    figures = {"frames": len(poses), "ground": body.ground, "min_height": float(min((p @ body.up).min() for p in poses)),
               "energy_start": energies[0], "energy_end": energies[-1], "energy_max": max(energies),
               "inverted_tets_end": int((volumes <= 0).sum()), "substeps": params["substeps"],
               "substeps_max": body.substeps}
    if log:
        log(f"simulation: lowest point {figures['min_height']:.3f} (ground {body.ground:.3f}), energy "
            f"{energies[0]:.3g} -> {energies[-1]:.3g} J, {body.substeps} substeps a frame at the end")
    return poses, figures
