"""The per-view, per-primitive preparation on the Triton backend: autograd ops around
prepare_kernels.py (the colours from the SH, the neural frame and boxes, the Gaussians' EWA
projection and boxes), each one launch forward and one backward."""

from __future__ import annotations

import torch

from radfield.core.backends.gpu.launch import PREPARE_OPTIONS, launching, padded
from radfield.util.transfer import to_device


class _SHColor(torch.autograd.Function):
    """max(Σ_k Y_k(v/|v|) sh_k + 0.5, 0) (prepare_kernels.py), differentiable w.r.t. sh and v."""

    @staticmethod
    def forward(ctx, sh, v, degree):
        from radfield.core.backends.gpu import prepare_kernels as K

        sh, v = sh.contiguous(), v.contiguous()
        out = v.new_empty(v.shape[0], 3)
        count = v.shape[0]
        with launching():
            K.sh_color_forward[(-(-count // K.BLOCK),)](sh, v, out, count, sh.shape[1], COEFFS=(degree + 1) ** 2,
                                                        BLOCK=K.BLOCK, **PREPARE_OPTIONS)
        ctx.degree = degree
        ctx.save_for_backward(sh, v)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        from radfield.core.backends.gpu import prepare_kernels as K

        sh, v = ctx.saved_tensors
        g_sh, g_v = torch.zeros_like(sh), torch.empty_like(v)
        count = v.shape[0]
        with launching():
            K.sh_color_backward[(-(-count // K.BLOCK),)](grad.contiguous(), sh, v, g_sh, g_v, count, sh.shape[1],
                                                         COEFFS=(ctx.degree + 1) ** 2, BLOCK=K.BLOCK, **PREPARE_OPTIONS)
        return g_sh, g_v, None


class _NeuralPrep(torch.autograd.Function):
    """The neural primitives' per-view tensors (m_cam (P, 3, 3), o_ell (P, 3), w_cam (P, N, 3), c (P, N),
    inv_smax (P,); prepare_kernels.py), differentiable w.r.t. means, log_scales, quats, w1 and b1;
    `view` = (o, R_cam row-major, ω0) in their dtype."""

    @staticmethod
    def forward(ctx, means, log_scales, quats, w1, b1, view):
        from radfield.core.backends.gpu import prepare_kernels as K

        inputs = [t.contiguous() for t in (means, log_scales, quats, w1, b1, view)]
        count, units = b1.shape
        outputs = (means.new_empty(count, 3, 3), means.new_empty(count, 3), w1.new_empty(count, units, 3),
                   b1.new_empty(count, units), means.new_empty(count))
        with launching():
            K.neural_prep_forward[(-(-count // K.BLOCK),)](*inputs, *outputs, count, units, NP=padded(units),
                                                           BLOCK=K.BLOCK, **PREPARE_OPTIONS)
        ctx.save_for_backward(*inputs[:4], inputs[5])
        return outputs

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads):
        from radfield.core.backends.gpu import prepare_kernels as K

        means, log_scales, quats, w1, view = ctx.saved_tensors
        count, units = w1.shape[:2]
        shapes = ((count, 3, 3), (count, 3), (count, units, 3), (count, units), (count,))
        grads = [means.new_zeros(shape) if g is None else g.contiguous() for g, shape in zip(grads, shapes)]
        out = [torch.empty_like(t) for t in (means, log_scales, quats, w1)] + [w1.new_empty(count, units)]
        with launching():
            K.neural_prep_backward[(-(-count // K.BLOCK),)](*grads, means, log_scales, quats, w1, view, *out, count,
                                                            units, NP=padded(units), BLOCK=K.BLOCK,
                                                            **PREPARE_OPTIONS)
        return (*out, None)


def neural_prep(prims, campos: torch.Tensor, cam_rot: torch.Tensor) -> tuple:
    """(m_cam, o_ell, w_cam, c, inv_smax) of splat/neural.py view_tensors (without its (W2, b2)) on
    Triton: one launch, and one for the backward."""
    view = torch.cat([campos, cam_rot.reshape(9), campos.new_full((1,), float(prims.omega0))])
    return _NeuralPrep.apply(prims.means, prims.log_scales, prims.quats, prims.w1, prims.b1, view)


class _GaussianPrep(torch.autograd.Function):
    """The splats' EWA projection (mean2d (P, 2), conic (P, 3), the covariance's (a, b, c) (P, 3);
    prepare_kernels.py), differentiable w.r.t. means_cam, log_scales and quats, and their pixel
    boxes (P, 4) int32 and visibility (P,) bool; `view` = (W (9), fx, fy, cx, cy, near, the Jacobian
    point's clamp (4)) in their dtype."""

    @staticmethod
    def forward(ctx, means_cam, log_scales, quats, view, width, height):
        from radfield.core.backends.gpu import prepare_kernels as K

        inputs = [t.contiguous() for t in (means_cam, log_scales, quats, view)]
        count, device = means_cam.shape[0], means_cam.device
        outputs = (means_cam.new_empty(count, 2), means_cam.new_empty(count, 3), means_cam.new_empty(count, 3),
                   torch.empty(count, 4, dtype=torch.int32, device=device), torch.empty(count, dtype=torch.int8, device=device))
        with launching():
            K.gaussian_prep_forward[(-(-count // K.BLOCK),)](*inputs, *outputs, count, width, height, BLOCK=K.BLOCK,
                                                             **PREPARE_OPTIONS)
        ctx.save_for_backward(*inputs)
        bounds, visible = outputs[3], outputs[4].bool()
        ctx.mark_non_differentiable(bounds, visible)
        return (*outputs[:3], bounds, visible)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_mean2d, g_conic, g_cov, _bounds, _visible):
        from radfield.core.backends.gpu import prepare_kernels as K

        means_cam, log_scales, quats, view = ctx.saved_tensors
        count = means_cam.shape[0]
        grads = [means_cam.new_zeros(count, width) if g is None else g.contiguous()
                 for g, width in ((g_mean2d, 2), (g_conic, 3), (g_cov, 3))]
        out = [torch.empty_like(t) for t in (means_cam, log_scales, quats)]
        with launching():
            K.gaussian_prep_backward[(-(-count // K.BLOCK),)](*grads, means_cam, log_scales, quats, view, *out, count,
                                                              BLOCK=K.BLOCK, **PREPARE_OPTIONS)
        return (*out, None, None, None)


def gaussian_prep(prims, frame) -> tuple:
    """(bounds, visible, (mean2d, conic, opacity)) of splat/gaussian.py (ewa_view and
    splat_bounds) on Triton: one launch, and one for the backward. The clamp of the Jacobian's point
    is the twin's, from the camera's numbers."""
    from radfield.core.splat.gaussian import jacobian_clamp

    camera = frame.camera
    numbers = torch.tensor([camera.fx, camera.fy, camera.cx, camera.cy, frame.near, *jacobian_clamp(camera)],
                           dtype=frame.means_cam.dtype)
    view = torch.cat([frame.w2c[:3, :3].reshape(9), to_device(numbers, frame.means_cam.device)])
    mean2d, conic, _, bounds, visible = _GaussianPrep.apply(frame.means_cam, prims.log_scales, prims.quats, view,
                                                            camera.width, camera.height)
    return bounds, visible, (mean2d, conic, torch.sigmoid(prims.opacities))


@torch.no_grad()
def neural_bounds(prims, frame) -> tuple[torch.Tensor, torch.Tensor]:
    """(bounds (P, 4) int32, visible (P,) bool) of splat/view.py ellipsoid_bounds in one launch."""
    from radfield.core.backends.gpu import prepare_kernels as K

    means_cam = frame.means_cam.detach().contiguous()
    count, camera = means_cam.shape[0], frame.camera
    view = torch.cat([frame.w2c[:3, :3].reshape(9), frame.intrinsics]).detach()
    bounds = torch.empty(count, 4, dtype=torch.int32, device=means_cam.device)
    visible = torch.empty(count, dtype=torch.int8, device=means_cam.device)
    with launching():
        K.neural_bounds[(-(-count // K.BLOCK),)](means_cam, prims.log_scales.detach().contiguous(),
                                                 prims.quats.detach().contiguous(), view, bounds, visible, count,
                                                 camera.width, camera.height, BLOCK=K.BLOCK, **PREPARE_OPTIONS)
    return bounds, visible.bool()


def sh_color(sh: torch.Tensor, v: torch.Tensor, degree: int) -> torch.Tensor:
    """Op "sh_color" on Triton: sh.sh_to_color(sh, normalize(v), degree) (v = μ − o) in one launch, and
    one for its backward."""
    if v.shape[0] == 0:   # no grid to launch: the twin's empty result
        from radfield.core.splat.sh import sh_to_color

        return sh_to_color(sh, torch.nn.functional.normalize(v, dim=-1), degree)
    return _SHColor.apply(sh, v, degree)
