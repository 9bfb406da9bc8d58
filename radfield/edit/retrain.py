"""Local retraining (Neural Impostor §4.2): refit a few primitives to a teacher, everything else frozen.

The teacher is a field whose primitives may carry a mask m(x) ∈ {0, 1} (a boolean field, eq. 13-15):
a masked primitive's optical depth along a ray is the quadrature (1/max s) ∫ m(x) σ(x) dℓ over its
chord (midpoint rule, `samples` points), an unmasked one's the closed form of the renderer. The
teacher image composites these exactly as the renderer does (centre-depth order, α ≤ 0.99, α <
1/255 skipped, stop below T = 1e-4): `teacher_render`, vectorised over (ray, primitive) pairs and
composited by the renderer's own routine (core/splat/composite.py: composite_pairs).

Two stages (eq. 12): stage 1 fits the MLP of the trainable primitives to the teacher's density
(Σ m_i σ_i / max s_i) at points sampled in their ellipsoids (L1); stage 2 fits all their parameters
to teacher renders from views around them (L1 on colour) with the fast renderer. Neural primitives only.

For a windowed model (prims.window) every σ here, at points and along rays, is the windowed
density 1.5 (1 − r²) σ (core/kinds/neural_density.py: density_window; the closed form windowed_optical_depth),
the student's in stage 1 included, and the fitted primitives keep the flag.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from radfield.core.geometry.camera_path import fibonacci_directions
from radfield.core.geometry.cameras import Camera, look_at, pixel_rays
from radfield.core.splat.composite import composite_pairs
from radfield.core.splat.kernels import ALPHA_MAX, ALPHA_MIN, ellipsoid_frame, neural_optical_depth, ray_ellipsoid, windowed_optical_depth
from radfield.core.train.losses import psnr
from radfield.core.kinds.neural import NeuralPrimitives
from radfield.core.kinds.neural_density import density_window, ellipsoid_radius_sq, neural_sigma
from radfield.core.render.rasterize import T_MIN, render
from radfield.core.splat.sh import sh_to_color

BACKGROUND = (1.0, 1.0, 1.0)
# local fits run for ~100 steps, not 30k: rates well above the training defaults (means × extent)
LR_STAGE1 = 2e-2
LR_STAGE2 = {"means": 2e-2, "log_scales": 1e-2, "quats": 5e-3, "sh": 2e-2, "w1": 1e-2, "b1": 1e-2, "w2": 1e-2, "b2": 2e-2}


# --- densities at points ---------------------------------------------------------------------


# --- the teacher: rays through masked primitives ---------------------------------------------

def ray_alphas(prims: NeuralPrimitives, origins: torch.Tensor, dirs: torch.Tensor, l_min: torch.Tensor,
               mask_id: np.ndarray, masks: list, samples: int = 64, chunk: int = 1024):
    """Pairs (ray, primitive, α) with α > 0 for rays o + ℓ d̂, ℓ ≥ l_min (float64 tensors (R, 3),
    (R,)): the closed form for primitives with mask_id −1, the masked quadrature for the others
    (masks[k] maps points (n, 3) float64 numpy -> bool (n,))."""
    p = prims.to(dtype=torch.float64)
    mask_id = torch.as_tensor(np.asarray(mask_id, np.int64))
    out_r, out_p, out_a = [], [], []
    m_all, smax_all = ellipsoid_frame(p.means, p.log_scales, p.quats)
    for lo in range(0, len(p), chunk):
        ids = torch.arange(lo, min(lo + chunk, len(p)))
        mu, smax = p.means[ids], smax_all[ids]
        rel = mu[None] - origins[:, None]                                    # (R, C, 3)
        along = (rel * dirs[:, None]).sum(-1)
        miss2 = (rel * rel).sum(-1) - along * along
        cand = (miss2 <= smax**2) & (along + smax > l_min[:, None])          # bounding sphere meets the ray
        r, c = torch.nonzero(cand, as_tuple=True)
        if r.numel() == 0:
            continue
        j = ids[c]
        o, d = origins[r], dirs[r]
        m = m_all[j]
        d_ell = torch.einsum("pij,pj->pi", m, d)
        l_in_raw, l_out, hit = ray_ellipsoid(torch.einsum("pij,pj->pi", m, o - p.means[j]), d_ell)
        l_in = torch.maximum(l_in_raw, l_min[r])
        hit = hit & (l_out > l_in)
        r, j, o, d, d_ell, l_in_raw, l_in, l_out = (t[hit] for t in (r, j, o, d, d_ell, l_in_raw, l_in, l_out))
        depth = torch.zeros(len(r), dtype=torch.float64)
        plain = mask_id[j] < 0
        if plain.any():
            q = j[plain]
            w = p.omega0 * p.w1[q]
            a = torch.einsum("pnj,pj->pn", w, d[plain])
            cc = torch.einsum("pnj,pj->pn", w, (o[plain] - p.means[q]) / smax_all[q, None]) + p.omega0 * p.b1[q]
            mlp = a, cc, p.w2[q], p.b2[q], 1.0 / smax_all[q]
            hits = torch.ones_like(l_in[plain], dtype=torch.bool)
            if p.window:   # the renderer's windowed closed form (near-plane clip from the unclipped entry)
                depth[plain] = windowed_optical_depth(l_in_raw[plain], l_in[plain], l_out[plain], hits,
                                                      (d_ell[plain] ** 2).sum(-1), *mlp)
            else:
                depth[plain] = neural_optical_depth(l_in[plain], l_out[plain], hits, *mlp)
        for k in torch.unique(mask_id[j][~plain]).tolist():
            sel = torch.nonzero(mask_id[j] == k).squeeze(1)
            depth[sel] = _masked_depth(p, j[sel], o[sel], d[sel], l_in[sel], l_out[sel], masks[k], samples)
        alpha = torch.clamp_max(-torch.expm1(-torch.clamp_min(depth, 0.0)), ALPHA_MAX)
        keep = alpha >= ALPHA_MIN
        out_r.append(r[keep]), out_p.append(j[keep]), out_a.append(alpha[keep])
    if not out_r:
        empty = torch.zeros(0, dtype=torch.int64)
        return empty, empty, torch.zeros(0, dtype=torch.float64)
    return torch.cat(out_r), torch.cat(out_p), torch.cat(out_a)


def _masked_depth(p, j, o, d, l_in, l_out, mask, samples: int) -> torch.Tensor:
    """(1/max s) ∫ m(x) σ_j(x) dℓ over [l_in, l_out] by the midpoint rule (eq. 15 per primitive;
    σ windowed where p.window: neural_sigma)."""
    out = torch.zeros(len(j), dtype=torch.float64)
    step = 1 << 14
    for lo in range(0, len(j), step):
        s = slice(lo, lo + step)
        t = (torch.arange(samples, dtype=torch.float64) + 0.5) / samples
        ell = l_in[s, None] + (l_out[s] - l_in[s])[:, None] * t                      # (n, K)
        x = o[s, None] + ell[..., None] * d[s, None]                                  # (n, K, 3)
        sub = p.select(j[s])
        sigma = neural_sigma(sub, x)
        inside = torch.as_tensor(mask(x.reshape(-1, 3).numpy())).reshape(sigma.shape)
        smax = sub.scales.amax(-1)
        out[s] = (sigma * inside).sum(-1) * (l_out[s] - l_in[s]) / samples / smax
    return out


def teacher_render(prims: NeuralPrimitives, camera: Camera, mask_id=None, masks=(), background=BACKGROUND,
                   near: float = 0.01, samples: int = 64) -> torch.Tensor:
    """(H, W, 3) float64 image of the masked field, composited as the renderer does."""
    mask_id = np.full(len(prims), -1) if mask_id is None else mask_id
    with torch.no_grad():
        dirs, norm = pixel_rays(camera, dtype=torch.float64)
        dirs, norm = dirs.reshape(-1, 3), norm.reshape(-1)
        origins = camera.center.expand_as(dirs)
        r, j, alpha = ray_alphas(prims, origins, dirs, near * norm, mask_id, list(masks), samples)
        p = prims.to(dtype=torch.float64)
        w2c = camera.w2c
        rank = torch.empty(len(p), dtype=torch.int64)   # the renderer's order: centre depth, stable
        rank[torch.argsort(p.means @ w2c[2, :3] + w2c[2, 3], stable=True)] = torch.arange(len(p))
        n = len(dirs)
        out = composite_pairs(r, rank[j], alpha, torch.zeros(n, dtype=torch.float64), T_MIN)
        colors = sh_to_color(p.sh, torch.nn.functional.normalize(p.means - camera.center, dim=-1), p.sh_degree)
        acc = torch.zeros(n, 3, dtype=torch.float64).index_add(0, out.pixel, out.weight[:, None] * colors[j[out.order]])
        image = acc + torch.exp(out.log_t)[:, None] * torch.tensor(background, dtype=torch.float64)
    return image.reshape(camera.height, camera.width, 3)


def opacity_from(prims: NeuralPrimitives, points: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Accumulated opacity 1 − Π(1 − α) (R,) of the field along rays leaving points (R, 3) in dirs (R, 3):
    an occupancy test, so every pair counts (t_min = 0: no early termination), and a product needs
    no depth order: the rank is each pair's own index, keeping ray_alphas' order along each ray."""
    o = torch.as_tensor(np.asarray(points, np.float64))
    d = torch.nn.functional.normalize(torch.as_tensor(np.asarray(dirs, np.float64)), dim=-1)
    with torch.no_grad():
        r, _, alpha = ray_alphas(prims, o, d, torch.zeros(len(o), dtype=torch.float64), np.full(len(prims), -1), [])
        log_t = composite_pairs(r, torch.arange(len(r)), alpha, torch.zeros(len(o), dtype=torch.float64), 0.0).log_t
    return (1 - torch.exp(log_t)).numpy()


# --- views and fitting -----------------------------------------------------------------------

def orbit_around(prims, idx, views: int, size: int) -> list[Camera]:
    """`views` cameras of size×size pixels on a sphere around primitives idx (Fibonacci
    directions), each framing the bounding sphere of their ellipsoids."""
    p = prims.select(torch.as_tensor(np.asarray(idx, np.int64))).to(dtype=torch.float64)
    means, reach = p.means.detach(), p.scales.detach().amax(-1)
    lo, hi = (means - reach[:, None]).amin(0), (means + reach[:, None]).amax(0)
    centre = (lo + hi) / 2
    radius = float(((hi - lo) / 2).norm()) or 1e-3
    dist = 3.0 * radius
    focal = (size / 2) / math.tan(math.asin(1 / 3.0) * 1.15)
    cams = []
    for k, direction in enumerate(fibonacci_directions(views)):
        eye = centre + dist * torch.from_numpy(direction)
        up = (0.0, 0.0, 1.0) if abs(direction[2]) < 0.95 else (0.0, 1.0, 0.0)
        cams.append(Camera(fx=focal, fy=focal, cx=size / 2, cy=size / 2, width=size, height=size,
                           c2w=look_at(eye.tolist(), centre.tolist(), up), name=f"local{k}"))
    return cams


def render_image(prims, camera: Camera, background=BACKGROUND) -> torch.Tensor:
    return render(prims, camera, background=background).color


def _inside_pairs(prims, points: torch.Tensor, chunk: int = 4096):
    """(point, primitive) index pairs with the point inside the primitive's ellipsoid."""
    with torch.no_grad():
        m, _ = ellipsoid_frame(prims.means.float(), prims.log_scales.float(), prims.quats.float())
        qs, ps = [], []
        for lo in range(0, len(points), chunk):
            rel = points[lo:lo + chunk, None] - prims.means.float()[None]
            inside = (torch.einsum("pij,qpj->qpi", m, rel).norm(dim=-1) <= 1.0)
            q, p = torch.nonzero(inside, as_tuple=True)
            qs.append(q + lo), ps.append(p)
    return (torch.cat(qs), torch.cat(ps)) if qs else (torch.zeros(0, dtype=torch.int64),) * 2


def _pair_window(prims, points: torch.Tensor, q_idx: torch.Tensor, p_idx: torch.Tensor):
    """The density window (pairs,) of primitive p_idx at point q_idx: 1.5 (1 − r²) for a
    windowed model, 1 for a hard-edged one (float32, as the stage-1 fit)."""
    if not prims.window:
        return 1.0
    with torch.no_grad():
        geometry = (t.float()[p_idx] for t in (prims.means, prims.log_scales, prims.quats))
        return density_window(prims, ellipsoid_radius_sq(*geometry, points[q_idx]))


def stage1_density(params: dict, omega0: float, points: torch.Tensor, q_idx: torch.Tensor, p_idx: torch.Tensor,
                   smax: torch.Tensor, window) -> torch.Tensor:
    """The student's density Σ_i σ_i(x_q) / max s_i (Q,) at the points, summed over the
    (point, primitive) pairs q_idx, p_idx with the point inside (geometry fixed: the means are
    detached), σ windowed by the pairs' `window` factors (_pair_window)."""
    w1, b1, w2, b2 = (params[n][p_idx] for n in ("w1", "b1", "w2", "b2"))
    u = (points[q_idx] - params["means"][p_idx].detach()) / smax[p_idx, None]
    sigma = ((torch.cos(omega0 * ((w1 * u[:, None]).sum(-1) + b1)) * w2).sum(-1) + b2) * window
    return torch.zeros(len(points), dtype=sigma.dtype).index_add(0, q_idx, sigma / smax[p_idx])


def _joined(frozen, trainable: dict, base):
    """The field frozen ∪ trainable as one primitive set (the renderer sorts by depth itself)."""
    out = base.map(lambda x: x)
    for name, tensor in frozen.tensors().items():
        setattr(out, name, torch.cat([tensor, trainable[name]], 0))
    return out


def _mean_psnr(prims, cameras, targets, background=BACKGROUND) -> float:
    with torch.no_grad():
        return float(np.mean([float(psnr(render_image(prims, c, background).double().clamp(0, 1), t.double().clamp(0, 1)))
                              for c, t in zip(cameras, targets)]))


def retrain(frozen: NeuralPrimitives, student: NeuralPrimitives, density_points: torch.Tensor,
            density_target: torch.Tensor, cameras: list[Camera], targets: list[torch.Tensor],
            steps1: int = 150, steps2: int = 150, seed: int = 0, log=lambda m: None):
    """Two-stage fit (module docstring) of `student` next to `frozen`. density_points (Q, 3) and
    density_target (Q,): the teacher's density of the retrained part. Returns the fitted student
    and figures (PSNR vs the teacher renders before and after, seconds per stage)."""
    g = torch.Generator().manual_seed(seed)
    # the trained parameters; per-primitive data that is not a parameter (rest_metric, written by a
    # preserve_opacity deformation) passes through unchanged, as the frozen primitives' does
    params = {n: t.detach().clone().float().requires_grad_(True) for n, t in student.tensors().items() if n in LR_STAGE2}
    extras = {n: t.detach().clone().float() for n, t in student.tensors().items() if n not in LR_STAGE2}
    frozen = frozen.to(dtype=torch.float32)
    if set(extras) != set(frozen.tensors()) - set(LR_STAGE2):
        raise ValueError("retrain: the frozen and the trained primitives hold different per-primitive data")
    if frozen.window != student.window:   # one field is drawn with one density (_joined keeps frozen's)
        raise ValueError("retrain: the frozen and the trained primitives have different density windows")
    figures = {"psnr_before": _mean_psnr(_joined(frozen, {**params, **extras}, frozen), cameras, targets)}

    # stage 1: MLP to the teacher's density at sampled points (eq. 12, first line)
    t0 = time.perf_counter()
    opt = torch.optim.Adam([params[n] for n in ("w1", "b1", "w2", "b2")], lr=LR_STAGE1)
    scale = float(density_target.abs().mean()) or 1.0
    pts, tgt = density_points.float(), density_target.float()
    # the geometry is fixed in this stage: find once which point lies in which ellipsoid
    q_idx, p_idx = _inside_pairs(student, pts)
    window = _pair_window(student, pts, q_idx, p_idx)   # fixed too: the student's σ windowed as the teacher's
    smax = student.scales.amax(-1).float()
    for _ in range(steps1 if len(q_idx) else 0):
        density = stage1_density(params, student.omega0, pts, q_idx, p_idx, smax, window)
        loss = (density - tgt).abs().mean() / scale
        opt.zero_grad()
        loss.backward()
        opt.step()
    figures["stage1_seconds"] = time.perf_counter() - t0
    figures["psnr_after_stage1"] = _mean_psnr(_joined(frozen, {**params, **extras}, frozen), cameras, targets)
    after1 = NeuralPrimitives(**{n: t.detach().clone().to(student.means.dtype) for n, t in {**params, **extras}.items()},
                              omega0=student.omega0, supersample=student.supersample, window=student.window)

    # stage 2: every parameter of the student to teacher renders (eq. 12, second line)
    t0 = time.perf_counter()
    extent = float(student.scales.amax()) if len(student) else 1.0
    opt = torch.optim.Adam([{"params": [params[n]], "lr": LR_STAGE2[n] * (extent if n == "means" else 1.0)} for n in params])
    targets32 = [t.float() for t in targets]
    base_lr = [group["lr"] for group in opt.param_groups]
    for step in range(steps2 if cameras else 0):
        for group, lr in zip(opt.param_groups, base_lr):     # exponential decay to a tenth
            group["lr"] = lr * 0.1 ** (step / max(steps2 - 1, 1))
        k = int(torch.randint(len(cameras), (1,), generator=g))
        img = render_image(_joined(frozen, {**params, **extras}, frozen), cameras[k])
        loss = (img - targets32[k]).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % 50 == 0:
            log(f"retrain stage 2: step {step}/{steps2}, L1 {float(loss.detach()):.4f}")
    figures["stage2_seconds"] = time.perf_counter() - t0
    fitted = NeuralPrimitives(**{n: t.detach().to(student.means.dtype) for n, t in {**params, **extras}.items()},
                              omega0=student.omega0, supersample=student.supersample, window=student.window)
    figures["psnr_after_stage2"] = _mean_psnr(_joined(frozen, fitted.tensors(), frozen), cameras, targets)
    # never leave the field further from the teacher (on these views) than an earlier stage did
    candidates = {"before": (figures["psnr_before"], student), "stage1": (figures["psnr_after_stage1"], after1),
                  "stage2": (figures["psnr_after_stage2"], fitted)}
    best = max(candidates, key=lambda k: candidates[k][0])
    figures["psnr_after"], figures["best_stage"] = candidates[best][0], best
    return candidates[best][1], figures


def fit_colors(prims, idx, cameras: list[Camera], targets: list[torch.Tensor], steps: int, seed: int = 0,
               background=BACKGROUND):
    """Appearance transfer: fit only the SH of primitives idx to target images (H, W, 3) seen by
    `cameras` over `background` (geometry frozen; L1, Adam, one random view a step). Returns the
    primitives with the new SH (others bit-identical) and PSNR figures."""
    g = torch.Generator().manual_seed(seed)
    idx = torch.as_tensor(np.asarray(idx, np.int64))
    sh = prims.sh[idx].detach().clone().float().requires_grad_(True)
    base = prims.to(dtype=torch.float32)
    keep = torch.ones(len(prims), dtype=torch.bool)
    keep[idx] = False
    frozen = base.select(keep)
    fixed = {n: t[idx] for n, t in base.tensors().items() if n != "sh"}

    def field(s):
        return _joined(frozen, {**fixed, "sh": s}, frozen)

    figures = {"psnr_before": _mean_psnr(field(sh), cameras, targets, background)}
    opt = torch.optim.Adam([sh], lr=LR_STAGE2["sh"])
    t0 = time.perf_counter()
    targets32 = [t.float() for t in targets]
    for _ in range(steps):
        k = int(torch.randint(len(cameras), (1,), generator=g))
        loss = (render_image(field(sh), cameras[k], background) - targets32[k]).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    figures["seconds"] = time.perf_counter() - t0
    figures["psnr_after"] = _mean_psnr(field(sh), cameras, targets, background)
    out = prims.map(lambda x: x.clone())
    out.sh[idx] = sh.detach().to(out.sh.dtype)
    return out, figures
