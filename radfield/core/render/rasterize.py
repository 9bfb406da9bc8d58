"""Differentiable splatting of neural primitives and 3D Gaussians: one functional entry point.

    render(prims, camera, background=...) -> Render(color (H,W,3), alpha (H,W), depth (H,W), meta)

Pipeline:
1. per primitive, once per view: camera-space depth, frustum culling, a tight projected bound
   (the dual conic of the bounding ellipsoid for neural primitives, 3σ of the EWA covariance for
   Gaussians), and everything that depends only on the camera centre (o', c_k, SH colour);
2. primitives sorted by depth;
3. front-to-back compositing (paper eq. 4) with early termination, by one of two implementations
   with the same semantics:
   - on the CPU, the fused C++ tile rasteriser (core/backends/fused.py, core/backends/csrc/view_kernels.cpp), the
     default, with fused ops for the colour and the neural frame of step 1;
   - the readable torch twin `_composite` (RADFIELD_KERNELS=torch, other devices): the pixels of
     each projected bound become flat (primitive, pixel) pairs, evaluated in depth-ordered chunks
     of at most `max_pairs` (pixels whose transmittance fell below `t_min` drop out of later
     chunks) and composited with segmented cumulative sums of log-transmittance.
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import torch

from radfield.core.backends import fused
from radfield.core.geometry.cameras import Camera
from radfield.core.render.kernels import alpha_from_optical_depth, ellipsoid_frame, gaussian_alpha, neural_optical_depth, ray_ellipsoid, windowed_optical_depth
from radfield.core.kinds.primitives import Gaussians, NeuralPrimitives, quat_to_rotmat
from radfield.core.render.sh import sh_parts, sh_to_color

T_MIN = 1e-4            # 3DGS early termination threshold on transmittance
EWA_BLUR = 0.3          # 3DGS low-pass filter added to the 2D covariance (pixels²)


class Render(NamedTuple):
    color: torch.Tensor  # (H, W, 3)
    alpha: torch.Tensor  # (H, W) accumulated opacity 1 − T
    depth: torch.Tensor  # (H, W) opacity-weighted mean camera-space depth of primitive centres (0 where empty)
    meta: dict


def render(prims: NeuralPrimitives | Gaussians, camera: Camera, *, background=(1.0, 1.0, 1.0), near: float = 0.01,
           sh_degree: int | None = None, max_pairs: int = 1 << 20, t_min: float = T_MIN) -> Render:
    """Render one view. Differentiable w.r.t. every tensor of `prims` (and `background` if a tensor).

    sh_degree: use SH bands up to this degree (default: all the model has).
    max_pairs: torch path only: pixel-primitive pairs evaluated at once (results do not depend
        on it). Under torch.no_grad() it bounds the working memory: one chunk's pair tensors at a
        time. With gradients it does NOT bound memory: autograd keeps every chunk's saved tensors
        until backward, so a differentiable torch-path render holds memory proportional to all the
        view's candidate pairs (`meta["candidate_pairs"]`), whatever max_pairs is: measured with
        float32 primitives (scripts/saved_memory.py torch, 3000 primitives, one 128×128 view)
        ≈ 420 bytes per pair for neural primitives and ≈ 120 for Gaussians, the same for
        max_pairs = 2^10 … 2^20. The fused CPU path keeps nothing per pair: its memory is
        O(pixels + per-tile primitive lists + per-primitive tensors), with or without gradients.
    """
    device, dtype = prims.means.device, prims.means.dtype
    height, width = camera.height, camera.width
    c2w = camera.c2w.to(device=device, dtype=dtype)
    w2c = torch.linalg.inv(c2w)
    campos = c2w[:3, 3]
    means_cam = prims.means @ w2c[:3, :3].T + w2c[:3, 3]
    depth = means_cam[:, 2]
    degree = prims.sh_degree if sh_degree is None else min(sh_degree, prims.sh_degree)
    use_fused = fused.available(device, dtype)
    parts = sh_parts(prims.sh)   # the trainer's (sh_dc, sh_rest), read in place by the fused op
    if use_fused and parts is not None:
        colors = fused.sh_color_parts(*parts, prims.means, campos, degree)
    elif use_fused:   # the same per-primitive quantities from fused C++ ops (core/backends/csrc/prepare_kernels.cpp)
        colors = fused.sh_color(prims.sh, prims.means - campos, degree)
    else:
        colors = sh_to_color(prims.sh, torch.nn.functional.normalize(prims.means - campos, dim=-1), degree)

    intrinsics = torch.tensor([camera.fx, camera.fy, camera.cx, camera.cy, near], device=device, dtype=dtype)
    if isinstance(prims, NeuralPrimitives):
        if use_fused:   # bounds and depth order in C++ too (prepare_kernels.cpp: neural_bounds)
            bounds, ids = fused.neural_bounds(means_cam, prims.log_scales, prims.quats, w2c[:3, :3], intrinsics,
                                              width, height, near)
            m_cam, o_ell, w_cam, c, inv_smax = fused.neural_prep(prims, campos, c2w[:3, :3])
            view = (m_cam, o_ell, w_cam, c, *_density_weights(prims, campos - prims.means), inv_smax)
        else:
            bounds, visible = _neural_bounds(prims, camera, w2c, means_cam, near)
            view = _neural_view(prims, campos, c2w[:3, :3])
    elif isinstance(prims, Gaussians):
        if use_fused:   # EWA projection, bounds and depth order in C++ (prepare_kernels.cpp)
            mean2d, conic, cov = fused.gaussian_prep(means_cam, prims.log_scales, prims.quats, w2c[:3, :3], intrinsics,
                                                     width, height, near)
            view = (mean2d, conic, torch.sigmoid(prims.opacities))
            bounds, ids = fused.gaussian_bounds(mean2d, cov, depth, width, height, near)
        else:
            view, cov = _gaussian_view(prims, camera, w2c, means_cam, near)
            bounds, visible = _gaussian_bounds(view[0], *cov, depth, camera, near)
    else:
        raise TypeError(f"cannot render {type(prims).__name__}")

    if use_fused:
        # the whole view in one C++ kernel (core/backends/csrc/view_kernels.cpp): same compositing rules; it
        # takes every per-primitive tensor with `ids` (the visible primitives front to back) and
        # gathers and scatters itself, so no autograd op of a gather is recorded here
        if isinstance(prims, NeuralPrimitives):
            out = fused.neural_view(bounds, ids, intrinsics, height, width, t_min, colors, depth, *view, window=prims.window)
        else:
            out = fused.gaussian_view(bounds, ids, height, width, t_min, colors, depth, *view)
        acc_color, acc_depth, transmittance, counters = out
        n_pairs, n_contrib, n_done, n_candidates = counters.tolist()
    else:
        ids = torch.nonzero(visible).squeeze(1)
        ids = ids[torch.argsort(depth[ids].detach(), stable=True)]   # front to back; position = depth rank
        bounds = bounds[ids]
        kernel = partial(_neural_block, window=prims.window) if isinstance(prims, NeuralPrimitives) else _gaussian_block
        acc_color, acc_depth, transmittance, (n_pairs, n_contrib, n_done) = _composite(
            kernel, [t[ids] for t in view], bounds, colors[ids], depth[ids], intrinsics, height, width, max_pairs, t_min)
        x0, y0, x1, y1 = bounds.unbind(-1)
        n_candidates = int(((x1 - x0 + 1) * (y1 - y0 + 1)).sum())

    bg = torch.as_tensor(background, device=device, dtype=dtype)
    color = acc_color + transmittance[..., None] * bg
    alpha = 1.0 - transmittance
    mean_depth = acc_depth / torch.clamp_min(alpha, 1e-10)
    meta = {"visible": int(ids.numel()), "pairs": n_pairs, "contributing_pairs": n_contrib,
            "candidate_pairs": n_candidates, "terminated_pixels": n_done}
    return Render(color, alpha, mean_depth, meta)


def _composite(kernel, view, bounds, colors, depth, intrinsics, height, width, max_pairs, t_min):
    """The readable torch twin of the fused view kernel: (Σ w c (H, W, 3), Σ w z (H, W), T (H, W),
    (evaluated pairs, composited pairs, terminated pixels)) for primitives in depth order."""
    device, dtype = colors.device, colors.dtype
    x0, y0, x1, y1 = bounds.unbind(-1)
    bw = x1 - x0 + 1
    counts = bw * (y1 - y0 + 1)
    padded = _padded_sizes(counts)
    rank = torch.arange(len(counts), device=device)

    n_pix = height * width
    log_t = torch.zeros(n_pix, device=device, dtype=torch.float64)   # log transmittance, included pairs
    done = torch.zeros(n_pix, device=device, dtype=torch.bool)        # pixels that terminated early
    acc_color = torch.zeros(n_pix, 3, device=device, dtype=dtype)
    acc_depth = torch.zeros(n_pix, device=device, dtype=dtype)
    n_pairs = n_contrib = 0
    for lo, hi in _chunks(counts, max_pairs):
        # within a depth chunk, primitives of similar footprint are evaluated as dense blocks
        # (primitive × its bounding-box pixels): parameters broadcast instead of being gathered per pair
        ranks, pix, alpha = [], [], []
        for size in torch.unique(padded[lo:hi]).tolist():
            sel = lo + torch.nonzero(padded[lo:hi] == size).squeeze(1)
            k = torch.arange(size, device=device)
            row = y0[sel, None] + k // bw[sel, None]
            col = x0[sel, None] + k % bw[sel, None]
            block_pix = torch.where(k < counts[sel, None], row * width + col, -1)   # -1: padding
            live = (block_pix >= 0) & ~done[block_pix.clamp_min(0)]
            n_pairs += int(live.sum())
            block_alpha = kernel(col.to(dtype) + 0.5, row.to(dtype) + 0.5, intrinsics, *(t[sel] for t in view))
            p, q = torch.nonzero(live & (block_alpha > 0), as_tuple=True)
            ranks.append(sel[p])
            pix.append(block_pix[p, q])
            alpha.append(block_alpha[p, q])
        ranks, pix, alpha = torch.cat(ranks), torch.cat(pix), torch.cat(alpha)
        order = torch.argsort(pix * len(rank) + ranks)                 # by pixel, then depth
        ranks, pix, alpha = ranks[order], pix[order], alpha[order]
        log_t_before, log_1m_alpha = _segmented_log_transmittance(pix, alpha, log_t)
        included = (log_t_before + log_1m_alpha >= math.log(t_min)).detach()
        weight = (alpha * torch.exp(log_t_before).to(dtype)) * included
        acc_color = acc_color.index_add(0, pix, weight[:, None] * colors[ranks])
        acc_depth = acc_depth.index_add(0, pix, weight * depth[ranks])
        log_t = log_t.index_add(0, pix, log_1m_alpha * included)
        done[pix[~included]] = True
        n_contrib += int(included.sum())
    transmittance = torch.exp(log_t).to(dtype).reshape(height, width)
    return (acc_color.reshape(height, width, 3), acc_depth.reshape(height, width), transmittance,
            (n_pairs, n_contrib, int(done.sum())))


# --- per-view preparation --------------------------------------------------------------------

def _neural_view(prims: NeuralPrimitives, campos: torch.Tensor, cam_rot: torch.Tensor) -> tuple:
    """What depends only on the primitive and the camera, computed once per view:
    M = S⁻¹Rᵀ, o' = M(o − μ), c_k = ω0 (W1_k·u0 + b1_k) with u0 = (o − μ)/max(s); and, because a
    pair's world direction is d̂ = R_cam d_cam/|d_cam|, the per-pair products M d̂ and ω0 W1 d̂
    become M R_cam and ω0 W1 R_cam applied to the camera-space pixel direction."""
    m, smax = ellipsoid_frame(prims.means, prims.log_scales, prims.quats)
    rel = campos - prims.means
    o_ell = (m * rel[:, None, :]).sum(-1)
    w = prims.omega0 * prims.w1
    c = (w * (rel / smax[:, None])[:, None, :]).sum(-1) + prims.omega0 * prims.b1
    w2, b2 = _density_weights(prims, rel)
    return m @ cam_rot, o_ell, w @ cam_rot, c, w2, b2, 1.0 / smax


def _density_weights(prims: NeuralPrimitives, rel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(W2, b2) as the pair kernels see them in this view (rel = o − μ); both the torch twin and
    the fused path (whose fused op computes the rest of `_neural_view`) take them from here."""
    w2, b2 = prims.w2, prims.b2
    if prims.rest_metric is not None:
        # preserve_opacity edits (edit/deform.py): optical depth in rest-space distance,
        # I·√(d̂ᵀGd̂); I is linear in (w2, b2), so the factor at the central ray d̂ = (μ − o)/|μ − o|
        # folds into them once per view (exact on that ray, README "Editing")
        g, d = prims.rest_metric, torch.nn.functional.normalize(-rel, dim=-1)
        quad = (g[:, :3] * d * d).sum(-1) + 2 * (g[:, 3] * d[:, 0] * d[:, 1] + g[:, 4] * d[:, 0] * d[:, 2] + g[:, 5] * d[:, 1] * d[:, 2])
        factor = torch.sqrt(torch.clamp_min(quad, 0.0))
        w2, b2 = w2 * factor[:, None], b2 * factor
    return w2, b2


def _neural_bounds(prims: NeuralPrimitives, camera: Camera, w2c, means_cam, near):
    """Tight pixel bounds of each projected bounding ellipsoid, from its dual conic
    C* = K (μμᵀ − Σ) Kᵀ (camera frame, Σ = R S² Rᵀ). An ellipsoid that straddles the near plane
    gets the whole image (the pair kernel clips rays at the near plane itself)."""
    with torch.no_grad():
        rot = w2c[:3, :3] @ quat_to_rotmat(prims.quats)
        rs = rot * torch.exp(prims.log_scales)[:, None, :]
        sigma = rs @ rs.transpose(1, 2)
        z_ext = torch.sqrt(sigma[:, 2, 2])
        z = means_cam[:, 2]
        in_front = z - z_ext > near
        visible = z + z_ext > near
        k = camera.K.to(means_cam)
        dual = k @ (means_cam[:, :, None] * means_cam[:, None, :] - sigma) @ k.T
        full = torch.tensor([0, 0, camera.width - 1, camera.height - 1], device=means_cam.device)
        box = _conic_box(dual, camera.width, camera.height)
        bounds = torch.where(in_front[:, None], box, full)
        return _clip_bounds(bounds, visible, camera)


def _conic_box(dual: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Integer pixel bounds (x0, y0, x1, y1) of the points inside a conic, from its dual: the tangent
    lines u = const solve C*_00 − 2u C*_02 + u² C*_22 = 0 (likewise for v)."""
    def extent(i):
        c_ii, c_i2, c_22 = dual[:, i, i], dual[:, i, 2], dual[:, 2, 2]
        root = torch.sqrt(torch.clamp_min(c_i2 * c_i2 - c_ii * c_22, 0.0))
        lo, hi = (c_i2 + root) / c_22, (c_i2 - root) / c_22
        return torch.minimum(lo, hi), torch.maximum(lo, hi)

    (u0, u1), (v0, v1) = extent(0), extent(1)
    # pixel j covers centre j + 0.5: first/last centres inside [u0, u1]
    box = torch.stack([torch.ceil(u0 - 0.5), torch.ceil(v0 - 0.5), torch.floor(u1 - 0.5), torch.floor(v1 - 0.5)], -1)
    big = float(max(width, height) + 1)
    return torch.nan_to_num(box, nan=-1.0).clamp(-big, big).long()


def _clip_bounds(bounds, visible, camera):
    x0, y0 = bounds[:, 0].clamp_min(0), bounds[:, 1].clamp_min(0)
    x1, y1 = bounds[:, 2].clamp_max(camera.width - 1), bounds[:, 3].clamp_max(camera.height - 1)
    visible = visible & (x1 >= x0) & (y1 >= y0)
    return torch.stack([x0, y0, x1, y1], -1), visible


def _gaussian_view(prims: Gaussians, camera: Camera, w2c, means_cam, near):
    """EWA splatting (Zwicker et al., as in 3DGS): ((2D mean, conic of J W Σ Wᵀ Jᵀ + 0.3 I,
    opacity), the 2D covariance's entries (a, b, c))."""
    x, y, z = means_cam.unbind(-1)
    zs = torch.where(z > near, z, torch.ones_like(z))
    # as 3DGS/gsplat: clamp the Jacobian's point to 1.3× the field of view, which keeps the
    # affine approximation of far off-screen splats from exploding
    margin_x, margin_y = 0.15 * camera.width / camera.fx, 0.15 * camera.height / camera.fy
    tx = zs * torch.clamp(x / zs, -camera.cx / camera.fx - margin_x, (camera.width - camera.cx) / camera.fx + margin_x)
    ty = zs * torch.clamp(y / zs, -camera.cy / camera.fy - margin_y, (camera.height - camera.cy) / camera.fy + margin_y)
    zero = torch.zeros_like(zs)
    jac = torch.stack([camera.fx / zs, zero, -camera.fx * tx / zs**2,
                       zero, camera.fy / zs, -camera.fy * ty / zs**2], -1).reshape(-1, 2, 3)
    rot = w2c[:3, :3] @ quat_to_rotmat(prims.quats)
    rs = rot * torch.exp(prims.log_scales)[:, None, :]
    t = jac @ rs
    cov = t @ t.transpose(1, 2)
    a, b, c = cov[:, 0, 0] + EWA_BLUR, cov[:, 0, 1], cov[:, 1, 1] + EWA_BLUR
    det = a * c - b * b
    conic = torch.stack([c, -b, a], -1) / det[:, None]
    mean2d = torch.stack([camera.fx * x / zs + camera.cx, camera.fy * y / zs + camera.cy], -1)
    return (mean2d, conic, torch.sigmoid(prims.opacities)), (a, b, c)


@torch.no_grad()
def _gaussian_bounds(mean2d, a, b, c, depth, camera: Camera, near):
    """The 3σ pixel box of each splat (largest eigenvalue of its covariance (a, b, c)); visible
    when in front of the near plane with a positive-definite covariance and a box in the image."""
    det = a * c - b * b
    lam_max = 0.5 * (a + c) + torch.sqrt(torch.clamp_min(0.25 * (a - c) ** 2 + b * b, 0.0))
    radius = torch.ceil(3.0 * torch.sqrt(lam_max))
    cx, cy = mean2d[:, 0], mean2d[:, 1]
    box = torch.stack([torch.ceil(cx - radius - 0.5), torch.ceil(cy - radius - 0.5),
                       torch.floor(cx + radius - 0.5), torch.floor(cy + radius - 0.5)], -1)
    big = float(max(camera.width, camera.height) + 1)
    return _clip_bounds(torch.nan_to_num(box, nan=-1.0).clamp(-big, big).long(), (depth > near) & (det > 0), camera)



# --- pair kernels (elementwise over pairs; gathers by index fuse under torch.compile) -----------

def _camera_directions(u, v, intrinsics):
    """Unit camera-space directions (P, A, 3) through image points (u, v) (P, A), and the ray
    distance of the near plane along each."""
    fx, fy, cx, cy, near = intrinsics.unbind()
    d = torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], -1)
    norm = torch.linalg.vector_norm(d, dim=-1)
    return d / norm[..., None], near * norm


def _neural_block(u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax, window: bool = False):
    """α of primitives (P,) over blocks of image points (P, A); `window`: the windowed density."""
    d, l_near = _camera_directions(u, v, intrinsics)
    d_ell = d @ m_cam.transpose(1, 2)                    # d' = S⁻¹Rᵀ d̂
    l_in_raw, l_out, hit = ray_ellipsoid(o_ell[:, None, :], d_ell)
    l_in = torch.maximum(l_in_raw, l_near)               # camera inside: start at the near plane
    a = d @ w_cam.transpose(1, 2)                        # a_k = ω0 W1_k · d̂
    mlp = c[:, None, :], w2[:, None, :], b2[:, None], inv_smax[:, None]
    if window:
        optical_depth = windowed_optical_depth(l_in_raw, l_in, l_out, hit, (d_ell * d_ell).sum(-1), a, *mlp)
    else:
        optical_depth = neural_optical_depth(l_in, l_out, hit, a, *mlp)
    return alpha_from_optical_depth(optical_depth)


def _gaussian_block(u, v, intrinsics, mean2d, conic, opacity):
    return gaussian_alpha(u - mean2d[:, None, 0], v - mean2d[:, None, 1], conic[:, None, :], opacity[:, None])


# --- binning and compositing helpers ---------------------------------------------------------

def _chunks(counts: torch.Tensor, max_pairs: int):
    """Consecutive ranges [lo, hi) of depth-sorted primitives holding about max_pairs pairs each
    (a primitive larger than max_pairs gets a chunk of its own)."""
    if counts.numel() == 0:
        return []
    ends = torch.cumsum(counts, 0)
    chunk = ((ends - counts) // max_pairs).tolist()
    out, lo = [], 0
    for i in range(1, len(chunk) + 1):
        if i == len(chunk) or chunk[i] != chunk[lo]:
            out.append((lo, i))
            lo = i
    return out


def _padded_sizes(counts: torch.Tensor) -> torch.Tensor:
    """Block size of each primitive: its pixel count rounded up a ×1.25 ladder (≤ 25% padding,
    and few distinct sizes, so few blocks)."""
    top = max(int(counts.max()) if counts.numel() else 1, 1)
    ladder = [4]
    while ladder[-1] < top:
        ladder.append(max(ladder[-1] + 1, int(ladder[-1] * 1.25)))
    ladder = torch.tensor(ladder, device=counts.device)
    return ladder[torch.searchsorted(ladder, counts)]


def _segmented_log_transmittance(pix: torch.Tensor, alpha: torch.Tensor, log_t: torch.Tensor):
    """For pairs sorted by (pixel, depth): log T before each pair = the pixel's log T from earlier
    chunks + the exclusive segmented cumsum of log(1 − α). float64: a running sum over a million
    pairs would lose the per-pixel values to cancellation in float32."""
    log_1m_alpha = torch.log1p(-alpha.double())
    csum = torch.cumsum(log_1m_alpha, 0) - log_1m_alpha              # exclusive running sum
    first = torch.ones_like(pix, dtype=torch.bool)
    first[1:] = pix[1:] != pix[:-1]
    seg = torch.cumsum(first, 0) - 1
    seg_start = torch.nonzero(first).squeeze(1)
    return log_t[pix] + csum - csum[seg_start][seg], log_1m_alpha
