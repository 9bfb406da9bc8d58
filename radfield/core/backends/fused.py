"""Fused CPU kernels (a C++/OpenMP torch extension, core/backends/csrc/) for the rasteriser.

    neural_view(bounds, order, intrinsics, H, W, t_min, colors, depth, *neural params) -> sums, T, counters
    gaussian_view(bounds, order, H, W, t_min, colors, depth, mean2d, conic, opacity)   -> sums, T, counters
    neural_bounds(...), gaussian_bounds(...) -> (bounds, order)   pixel bounds and depth order
    gaussian_prep(means_cam, log_scales, quats, ...) -> mean2d, conic, cov   EWA projection
    sh_color(sh, v, degree), neural_prep(prims, campos, cam_rot)   per-view preparation
    sh_color_parts(sh_dc, sh_rest, means, campos, degree)          the colour from the trainer's SH tensors
    relight_view_dc(means, quats, sh, w1, b1, w2, b2, campos, light) a relightable kind's degree-0 SH in a view
    gaussian_accumulate(...), neural_accumulate(...)               the densification statistics of a view
    ssim_map(x, y, taps, pad, c1, c2), anisotropy(log_scales)      the loss (core/train/losses.py)
    photometric(x, y, taps, lambda_dssim, c1, c2)                  L1 + D-SSIM of a step in one op
    neural_block(...), gaussian_block(...)    the pair kernels alone (the tests' window on them)
    available(device=None, dtype=None) -> bool, build_error() -> str | None

The view kernels composite a whole view per 16×16 tile (view_kernels.cpp, the method is in its
header comment); the per-view ops replace their torch twins in core/splat/neural.py, core/splat/gaussian.py
and core/splat/sh.py (`view_tensors`, `ewa_view`, `sh_to_color`), and the block kernels have the
signatures and semantics of the kinds' `pair_alpha`. Every op has a hand-written backward; the torch twins stay the
readable references the tests compare against.

The extension is compiled at first use (1–3 minutes on a busy 2-core machine; needs g++ and
ninja) and cached on disk by torch (TORCH_EXTENSIONS_DIR, default ~/.cache/torch_extensions), so
later processes only load it (~0.1 s). Which calls run here is decided by the kernel-backend seam
(radfield.core.backends, backend "fused-cpu"): `RADFIELD_KERNELS=torch` forces the pure-torch path;
if the build fails, one warning says so and the torch path is used (tests/test_fused.py fails under CI=true).
"""

from __future__ import annotations

import contextlib
import io
import logging
import time
import warnings
from pathlib import Path

import torch

from radfield.core.backends.seam import forced_torch
from radfield.core.splat.kernels import WINDOW_GAIN

_CSRC = Path(__file__).resolve().parent / "csrc"
_SOURCES = [_CSRC / "block_kernels.cpp", _CSRC / "view_kernels.cpp", _CSRC / "prepare_kernels.cpp",
            _CSRC / "loss_kernels.cpp", _CSRC / "strategy_kernels.cpp", _CSRC / "positivity_kernels.cpp",
            _CSRC / "relight_kernels.cpp"]
_NAME = "radfield_kernels"   # the build's name: one build per SIMD level (_build_name)
_STALE_LOCK_SECONDS = 600   # a build lock older than this was left by a killed build
_state: dict = {"tried": False, "ops": None, "error": None}


def _simd_flags() -> list[str]:
    """Compile for the SIMD level torch itself dispatches to on this machine: ATen's Vectorized<T>
    (sin, cos, exp through Sleef) is a header whose width is chosen by these defines and -m flags.
    The build is per machine anyway (cached in the user's home); ATEN_CPU_CAPABILITY lowers it."""
    capability = torch.backends.cpu.get_cpu_capability()
    if capability == "AVX512":
        return ["-DCPU_CAPABILITY=AVX512", "-DCPU_CAPABILITY_AVX512",
                "-mavx512f", "-mavx512bw", "-mavx512vl", "-mavx512dq", "-mfma"]
    if capability == "AVX2":
        return ["-DCPU_CAPABILITY=AVX2", "-DCPU_CAPABILITY_AVX2", "-mavx2", "-mfma", "-mf16c"]
    return ["-DCPU_CAPABILITY=DEFAULT"]   # portable Vectorized<T>: scalar libm calls


def _build_name() -> str:
    """One cached build per SIMD level (radfield_kernels_avx512, _avx2, _default): lowering the level
    with ATEN_CPU_CAPABILITY (CI runs the numerics tests once more at AVX2) then loads its own build
    instead of recompiling over the other one each time the level changes."""
    return f"{_NAME}_{torch.backends.cpu.get_cpu_capability().lower()}"


class _NoCudaRuntimeLine(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return "No CUDA runtime is found" not in record.getMessage()


def _cpp_extension():
    """torch.utils.cpp_extension, imported without the line a CUDA build of torch writes at that
    import on a machine with a CUDA toolkit but no visible GPU ("No CUDA runtime is found, using
    CUDA_HOME=…": a print in torch 2.4, a logger warning later). These kernels are CPU-only, and the
    line would stand before every command's output, its one-line errors included, once a process."""
    logger = logging.getLogger("torch.utils.cpp_extension")
    quiet = _NoCudaRuntimeLine()
    logger.addFilter(quiet)
    try:
        with contextlib.redirect_stderr(io.StringIO()):
            from torch.utils import cpp_extension
    finally:
        logger.removeFilter(quiet)
    return cpp_extension


def _build():
    """Compile (or load the cached build of) the extension; returns torch.ops.radfield."""
    cpp_extension = _cpp_extension()

    # torch waits forever on the lock file of a build that was killed midway: clear a stale one
    try:
        lock = Path(cpp_extension._get_build_directory(_build_name(), verbose=False)) / "lock"
        if time.time() - lock.stat().st_mtime > _STALE_LOCK_SECONDS:
            lock.unlink(missing_ok=True)
    except (OSError, AttributeError):   # no lock (the usual case), or torch's private helper moved
        pass
    cpp_extension.load(
        name=_build_name(),
        sources=[str(p) for p in _SOURCES],
        extra_include_paths=[str(_CSRC)],
        # IEEE semantics kept (no -ffast-math); -fno-math-errno as torch's own build, so that
        # sqrt is an instruction (and vectorises) instead of a libm call that may set errno;
        # no FMA contraction: with it GCC fuses a·b + c wherever -mfma allows, so AVX2/AVX-512
        # builds rounded differently from the default build and from torch's eager twins, which
        # decided whether an ill-conditioned float32 gradient landed just inside or outside a
        # test bound that was relative to the twin's own error. -fno-trapping-math changes no
        # result either (nothing is reordered or contracted), but lets a loop with a guarded
        # division (sinc at x = 0, the window's series below |x| = 1, a missed chord) divide on
        # every lane and select: without it GCC vectorises such loops only with AVX-512's masked
        # division, and the AVX2 build ran the neural primitive's sinc and window scalar (a
        # branch-free rewrite does not help: GCC sinks the division back under the branch)
        extra_cflags=["-O3", "-fopenmp", "-fno-math-errno", "-fno-trapping-math", "-ffp-contract=off",
                      *_simd_flags()],
        extra_ldflags=["-fopenmp"],
        is_python_module=False,   # registers torch.ops.radfield.* (TORCH_LIBRARY), no pybind11
        verbose=False,
    )
    return torch.ops.radfield


def _ops():
    if not _state["tried"]:
        _state["tried"] = True
        try:
            _state["ops"] = _build()
        except Exception as exc:  # no compiler, no ninja, unwritable cache, compile error
            reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            _state["error"] = f"{type(exc).__name__}: {reason[:200]}"
            warnings.warn(f"radfield: fused CPU kernels unavailable ({type(exc).__name__}: {reason[:200]}); "
                          "using the slower torch kernels", RuntimeWarning, stacklevel=3)
    return _state["ops"]


def build_error() -> str | None:
    """Why the kernels are unavailable: the build's first error line, RADFIELD_KERNELS=torch, or None."""
    if forced_torch():
        return "RADFIELD_KERNELS=torch"
    _ops()
    return _state["error"]


def available(device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> bool:
    """True when the fused kernels can run tensors on `device` with `dtype` (builds them on the
    first call). False on non-CPU devices, for other dtypes than float32/float64, with
    RADFIELD_KERNELS=torch, or when the build failed."""
    if forced_torch():
        return False
    if device is not None and torch.device(device).type != "cpu":
        return False
    if dtype is not None and dtype not in (torch.float32, torch.float64):
        return False
    return _ops() is not None


def _prepared(u, v, *params):
    """Contiguous tensors, with u and v broadcast to (P, A) as the torch twins broadcast them
    against the primitives' parameters (P, ...)."""
    u, v = torch.broadcast_tensors(u, v)
    shape = torch.broadcast_shapes(u.shape, (params[-1].shape[0], 1))
    return [t.contiguous() for t in (u.expand(shape), v.expand(shape), *params)]


class _NeuralBlock(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax, gain):
        args = _prepared(u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax)
        ctx.gain = gain
        ctx.save_for_backward(*args)
        return _ops().neural_block_forward(*args, gain)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_alpha):
        args = ctx.saved_tensors
        grads = _ops().neural_block_backward(grad_alpha.contiguous(), *args, ctx.gain)
        return None, None, None, *grads, None


class _GaussianBlock(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, v, intrinsics, mean2d, conic, opacity):
        args = _prepared(u, v, mean2d, conic, opacity)
        ctx.save_for_backward(*args)
        return _ops().gaussian_block_forward(*args)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_alpha):
        grads = _ops().gaussian_block_backward(grad_alpha.contiguous(), *ctx.saved_tensors)
        return None, None, None, *grads


def neural_block(u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax, window: bool = False) -> torch.Tensor:
    """α of neural primitives (P,) over blocks of image points u, v (P, A); see
    splat/neural.py: pair_alpha (paper eq. 7–9; `window`: the windowed density)."""
    return _NeuralBlock.apply(u, v, intrinsics, m_cam, o_ell, w_cam, c, w2, b2, inv_smax, _gain(window))


def _gain(window: bool) -> float:
    """The kernels' window argument: the window's 1.5, or 0 for the hard-edged ellipsoid."""
    return WINDOW_GAIN if window else 0.0


def gaussian_block(u, v, intrinsics, mean2d, conic, opacity) -> torch.Tensor:
    """α of 2D Gaussian splats (P,) over blocks of image points u, v (P, A); see
    splat/gaussian.py: pair_alpha."""
    return _GaussianBlock.apply(u, v, intrinsics, mean2d, conic, opacity)


# --- whole-view rasteriser (core/backends/csrc/view_kernels.cpp) -----------------------------------------

class _View(torch.autograd.Function):
    """Composited sums of one view: (Σ w c (H, W, 3), Σ w z (H, W), T (H, W), counters (4,)),
    differentiable w.r.t. colors, depth and the kind's per-primitive tensors."""

    @staticmethod
    def forward(ctx, kind, bounds, order, intrinsics, height, width, t_min, gain, colors, depth, *params):
        inputs = [t.contiguous() for t in (colors, depth, *params)]
        bounds, order = bounds.contiguous(), order.contiguous()
        lead = (bounds, intrinsics.contiguous()) if kind == "neural" else (bounds,)
        tail = (gain,) if kind == "neural" else ()
        acc_color, acc_depth, trans, trans64, last, offsets, entries, used, counters, *gathered = getattr(
            _ops(), f"{kind}_view_forward")(bounds, order, *lead[1:], *inputs, height, width, t_min, *tail)
        # gathered: bounds and the per-primitive inputs in depth order, which the backward reads
        ctx.kind, ctx.intrinsics, ctx.count, ctx.tail = kind, lead[1:], bounds.shape[0], tail
        ctx.save_for_backward(*gathered, trans64, last, offsets, entries, used, order)
        ctx.mark_non_differentiable(counters)
        return acc_color, acc_depth, trans, counters

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_color, g_depth, g_trans, _):
        bounds, *inputs, trans64, last, offsets, entries, used, order = ctx.saved_tensors
        dtype = inputs[0].dtype
        grads = [torch.zeros(s, dtype=dtype) if g is None else g.contiguous()
                 for g, s in zip((g_color, g_depth, g_trans), (last.shape + (3,), last.shape, last.shape))]
        out = getattr(_ops(), f"{ctx.kind}_view_backward")(*grads, bounds, *ctx.intrinsics, *inputs, trans64, last,
                                                            offsets, entries, used, order, ctx.count, *ctx.tail)
        return None, None, None, None, None, None, None, None, *out


def neural_view(bounds, order, intrinsics, height, width, t_min, colors, depth, m_cam, o_ell, w_cam, c, w2, b2,
                inv_smax, window: bool = False):
    """Front-to-back compositing of neural primitives over a whole view in one fused kernel:
    returns (Σ w_i c_i (H, W, 3), Σ w_i z_i (H, W), T (H, W), counters (evaluated pairs,
    composited pairs, terminated pixels, candidate pairs)). order (V,) int64: the primitives to
    draw, front to back, each once; bounds (P, 4) int64 inclusive pixel boxes, inside the image
    for those in `order`; the per-primitive tensors (P, ...) as splat/neural.py: view_tensors returns
    them (gradients are zero for the primitives not in `order`). The op keeps copies of them in
    depth order for its backward (memory O(V) per-primitive rows, nothing per pair).
    `window`: the windowed density (kinds/neural_density.py: density_window)."""
    return _View.apply("neural", bounds, order, intrinsics, height, width, t_min, _gain(window), colors, depth,
                       m_cam, o_ell, w_cam, c, w2, b2, inv_smax)


def gaussian_view(bounds, order, height, width, t_min, colors, depth, mean2d, conic, opacity):
    """As neural_view, for EWA splats (mean2d (P, 2), conic (P, 3), opacity (P,))."""
    return _View.apply("gaussian", bounds, order, None, height, width, t_min, None, colors, depth, mean2d, conic,
                       opacity)


def neural_bounds(means_cam, log_scales, quats, w2c_rot, intrinsics, width: int, height: int, near: float):
    """splat/view.py: ellipsoid_bounds and the depth sort in one op (no gradient): (bounds (P, 4) int64,
    order (V,) int64, the visible primitives by camera-space depth means_cam[:, 2], stable)."""
    args = [t.detach().contiguous() for t in (means_cam, log_scales, quats, w2c_rot, intrinsics)]
    return tuple(_ops().neural_bounds(*args, width, height, float(near)))


def gaussian_bounds(mean2d, cov, depth, width: int, height: int, near: float):
    """splat/gaussian.py: splat_bounds and the depth sort in one op (no gradient), from the splats'
    2D means (P, 2), covariances (a, b, c) (P, 3) and depths (P,): (bounds, order) as neural_bounds."""
    args = [t.detach().contiguous() for t in (mean2d, cov, depth)]
    return tuple(_ops().gaussian_bounds(*args, width, height, float(near)))


# --- per-view preparation (core/backends/csrc/prepare_kernels.cpp) ---------------------------------------

class _SHColor(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sh, v, degree):
        sh, v = sh.contiguous(), v.contiguous()
        ctx.degree = degree
        ctx.save_for_backward(sh, v)
        return _ops().sh_color_forward(sh, v, degree)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        g_sh, g_v = _ops().sh_color_backward(grad.contiguous(), *ctx.saved_tensors, ctx.degree)
        return g_sh, g_v, None


class _NeuralPrep(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, log_scales, quats, w1, b1, campos, cam_rot, omega0):
        args = [t.contiguous() for t in (means, log_scales, quats, w1, b1, campos, cam_rot)]
        ctx.omega0 = float(omega0)
        ctx.save_for_backward(*args)
        return tuple(_ops().neural_prep_forward(*args, ctx.omega0))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads):
        args = ctx.saved_tensors
        grads = [torch.zeros_like(o) if g is None else g.contiguous() for g, o in zip(grads, _prep_shapes(args))]
        out = _ops().neural_prep_backward(*grads, *args, ctx.omega0)
        return (*out, None, None, None)


def _prep_shapes(args):
    means, _, _, w1, b1, _, _ = args
    p, n = b1.shape
    return [means.new_empty(p, 3, 3), means.new_empty(p, 3), w1.new_empty(p, n, 3), b1.new_empty(p, n), means.new_empty(p)]


def sh_color(sh, v, degree: int) -> torch.Tensor:
    """sh.sh_to_color(sh, normalize(v), degree) in one fused op (v = μ − o, unnormalised)."""
    return _SHColor.apply(sh, v, degree)


class _SHColorParts(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sh_dc, sh_rest, means, campos, degree):
        args = [t.contiguous() for t in (sh_dc, sh_rest, means, campos)]
        ctx.degree = degree
        ctx.save_for_backward(*args)
        return _ops().sh_parts_color_forward(*args, degree)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        g_dc, g_rest, g_means = _ops().sh_parts_color_backward(grad.contiguous(), *ctx.saved_tensors, ctx.degree)
        g_campos = -g_means.sum(0) if ctx.needs_input_grad[3] else None   # v = μ − o
        return g_dc, g_rest, g_means, g_campos, None


def sh_color_parts(sh_dc, sh_rest, means, campos, degree: int) -> torch.Tensor:
    """sh_color(cat([sh_dc, sh_rest], 1), means − campos, degree) in one fused op that reads the
    two SH tensors (P, 1, 3), (P, K − 1, 3) where they are: no concatenation and no v tensor,
    forward or backward (the gradients of sh_dc, sh_rest and the means are written directly)."""
    return _SHColorParts.apply(sh_dc, sh_rest, means, campos, degree)


def neural_prep(prims, campos, cam_rot) -> tuple:
    """The ellipsoid frame and MLP phases of splat/neural.py: view_tensors in one fused op:
    (m_cam, o_ell, w_cam, c, inv_smax); (w2, b2) come from splat/neural.py: density_weights."""
    return _NeuralPrep.apply(prims.means, prims.log_scales, prims.quats, prims.w1, prims.b1, campos, cam_rot,
                             prims.omega0)


# --- the relightable kinds' colour of a view (core/backends/csrc/relight_kernels.cpp) ---------------------

class _RelightViewDC(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, sh, w1, b1, w2, b2, campos, light_xyz, point, intensity):
        args = [t.contiguous() for t in (means, quats, sh, w1, b1, w2, b2, campos, light_xyz)]
        ctx.light = (bool(point), float(intensity))
        dc, hidden, slope = _ops().relight_view_dc_forward(*args, *ctx.light)
        ctx.save_for_backward(*args, hidden, slope)   # the backward then needs no exp or log
        return dc

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        want_view = ctx.needs_input_grad[7]
        *grads, g_view = _ops().relight_view_dc_backward(grad.contiguous(), *ctx.saved_tensors, *ctx.light, want_view)
        g_campos = -g_view.sum(0) if want_view else None   # v = μ − o
        return (*grads, g_campos, None, None, None)


def relight_view_dc(means, quats, sh, w1, b1, w2, b2, campos, light) -> torch.Tensor:
    """kinds/relight.py: view_sh in one fused op for SH of degree 0 (sh (P, 1, 3)): the degree-0 SH
    (P, 1, 3) of each primitive's colour (c_dc + c_θ(Rᵀd, Rᵀd_l)) · E (eq. 14) seen from campos (3,)
    under `light` (cameras.Light: a point light's position or a directional light's direction, and
    its intensity); differentiable w.r.t. means, quats, sh, the network (w1, b1, w2, b2) and campos."""
    point = light.position is not None
    light_xyz = means.new_tensor(light.position if point else light.direction)
    return _RelightViewDC.apply(means, quats, sh, w1, b1, w2, b2, campos, light_xyz, point, float(light.intensity))


# --- the loss (core/backends/csrc/loss_kernels.cpp) -------------------------------------------------------

class _SSIMMoments(torch.autograd.Function):
    """An op of loss_kernels.cpp that blurs the SSIM moments of x, y (the SSIM map, or the whole
    photometric loss): `{op}_forward(x, y, taps, a, c1, c2)` returns (output, moments), and
    `{op}_backward(grad, x, y, taps, moments, a, c1, c2)` the gradient w.r.t. x; `a` is the op's
    own constant (the padding, or λ of D-SSIM)."""

    @staticmethod
    def forward(ctx, op, x, y, taps, a, c1, c2):
        x, y, taps = x.contiguous(), y.contiguous(), taps.contiguous()
        out, moments = getattr(_ops(), f"{op}_forward")(x, y, taps, a, c1, c2)
        ctx.op, ctx.constants = op, (a, c1, c2)
        ctx.save_for_backward(x, y, taps, moments)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        x, y, taps, moments = ctx.saved_tensors
        g_x = getattr(_ops(), f"{ctx.op}_backward")(grad.contiguous(), x, y, taps, moments, *ctx.constants)
        return None, g_x, None, None, None, None, None


class _Anisotropy(torch.autograd.Function):
    @staticmethod
    def forward(ctx, log_scales):
        log_scales = log_scales.contiguous()
        ctx.save_for_backward(log_scales)
        return _ops().anisotropy_forward(log_scales)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        return _ops().anisotropy_backward(grad.contiguous(), *ctx.saved_tensors)


def ssim_map(x, y, taps, pad: int, c1: float, c2: float) -> torch.Tensor:
    """The SSIM map (B, Ho, Wo, C) of images x, y (B, H, W, C) with the separable window `taps`
    (11,) and zero padding `pad` (0 or 5), differentiable w.r.t. x only; see losses.ssim."""
    return _SSIMMoments.apply("ssim_map", x, y, taps, int(pad), float(c1), float(c2))


def photometric(x, y, taps, lambda_dssim: float, c1: float, c2: float) -> torch.Tensor:
    """(1 − λ) mean|x − y| + λ (1 − mean SSIM map) of images x, y (B, H, W, C) with the "same"
    map (zero padding 5) and the separable window `taps` (11,), in one op (the loss of a training
    step, losses.photometric without a mask); differentiable w.r.t. x only. Its gradient is the
    composition's bit for bit; the value differs from torch's float reductions in the last bits."""
    return _SSIMMoments.apply("photometric", x, y, taps, float(lambda_dssim), float(c1), float(c2))


def anisotropy(log_scales) -> torch.Tensor:
    """losses.anisotropy (mean std(s / min(s))) in one fused op."""
    return _Anisotropy.apply(log_scales)


class _GaussianPrep(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means_cam, log_scales, quats, w2c_rot, intrinsics, width, height, near):
        args = [t.contiguous() for t in (means_cam, log_scales, quats, w2c_rot.detach(), intrinsics.detach())]
        ctx.constants = (int(width), int(height), float(near))
        ctx.save_for_backward(*args)
        mean2d, conic, cov = _ops().gaussian_prep_forward(*args, *ctx.constants)
        ctx.mark_non_differentiable(cov)
        return mean2d, conic, cov

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_mean2d, g_conic, _):
        args = ctx.saved_tensors
        grads = [torch.zeros_like(args[0][:, :k]) if g is None else g.contiguous() for g, k in ((g_mean2d, 2), (g_conic, 3))]
        out = _ops().gaussian_prep_backward(*grads, *args, *ctx.constants)
        return (*out, None, None, None, None, None)


def gaussian_prep(means_cam, log_scales, quats, w2c_rot, intrinsics, width: int, height: int, near: float):
    """The EWA projection of splat/gaussian.py: ewa_view in one fused op: (mean2d (P, 2), conic (P, 3),
    cov (P, 3) = the 2D covariance's (a, b, c) with the blur, not differentiable), from the
    camera-space means (P, 3); differentiable w.r.t. means_cam, log_scales and quats."""
    return _GaussianPrep.apply(means_cam, log_scales, quats, w2c_rot, intrinsics, width, height, near)


# --- population control (core/backends/csrc/strategy_kernels.cpp) ----------------------------------------

def gaussian_accumulate(grad, count, means, log_scales, grad_means, w2c, normals, radius_scale: float, near: float,
                        fx: float, fy: float, width: int, height: int) -> None:
    """strategy._Strategy.accumulate for Gaussians in one op, in place on the accumulators grad
    and count (P,): the frustum test (w2c (3, 4), the side planes' unit normals (4, 3)) and the
    screen-space gradient signal of grad_means (P, 3). No gradient."""
    args = [t.detach().contiguous() for t in (means, log_scales, grad_means, w2c, normals)]
    _ops().gaussian_accumulate(grad, count, *args, float(radius_scale), float(near), float(fx), float(fy),
                               float(width), float(height))


def neural_accumulate(grad, count, means, log_scales, g_w1, g_b1, g_w2, g_b2, w2c, normals, radius_scale: float,
                      near: float) -> None:
    """As gaussian_accumulate, with the MLP-gradient signal of neural primitives."""
    args = [t.detach().contiguous() for t in (means, log_scales, g_w1, g_b1, g_w2, g_b2, w2c, normals)]
    _ops().neural_accumulate(grad, count, *args, float(radius_scale), float(near))


def project_nonnegative_(w2, b2, mask) -> None:
    """positivity.project_nonnegative in place on the rows of w2 (P, N) and b2 (P,) where the
    bool mask (P,) is set (the others untouched). No gradient."""
    _ops().project_nonnegative_(w2, b2, mask.contiguous())
