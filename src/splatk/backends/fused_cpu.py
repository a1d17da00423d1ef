"""Fused native versions of the torch ops around the rasteriser (the ``cpu`` backend's helpers).

With the native rasteriser, a training iteration at 50k primitives on 400x400 spent 75% of its
time in torch ops: the separable SSIM convolutions (~75 ms forward+backward), the EWA projection
(~35 ms) and SH colour (~20 ms), each dozens of small kernels and autograd nodes. The C++ in
``csrc/`` (``ssim_ops.cpp``, ``project_ops.cpp``, ``sh_ops.cpp``) computes each in one pass with a
hand-written backward. The torch versions (``metrics/ssim.py``, ``functional/projection.py``, ``functional/sh.py``) stay the
specification; ``tests/backends/test_fused_ops.py`` checks these against them.

:class:`splatk.backends.cpu_backend.CpuBackend` is where they are used: ``--backend cpu`` / ``auto``
speeds up the whole iteration and ``--backend torch`` stays pure torch.
"""
from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from . import cpu_native


def _ext():
    ext = cpu_native.load_extension()
    if ext is None:
        raise RuntimeError(f"native ops unavailable: {cpu_native.unavailable_reason()}")
    return ext


# ---- SSIM ------------------------------------------------------------------------------------
class _SSIMMean(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, y, window):
        mean, partials = _ext().ssim_forward(x, y, window, ctx.needs_input_grad[0],
                                             torch.get_num_threads())
        ctx.save_for_backward(x, y, window, partials)
        return mean

    @staticmethod
    @once_differentiable
    def backward(ctx, v_mean):
        x, y, window, partials = ctx.saved_tensors
        v_x = _ext().ssim_backward(x, y, window, partials, float(v_mean), torch.get_num_threads())
        return v_x, None, None


def ssim_mean_fused(img: torch.Tensor, ref: torch.Tensor, window_size: int = 11,
                    sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM ('same' zero padding, as ``metrics.ssim.ssim``) of img [H, W, C] against
    ref [H, W, C]. Differentiable in ``img`` only (``ref`` is the photo)."""
    from ..metrics.ssim import gaussian_window

    if ref.requires_grad:
        raise ValueError("ssim_mean_fused: no gradient with respect to the reference image")
    dtype = torch.float64 if torch.float64 in (img.dtype, ref.dtype) else torch.float32
    x = img.to(dtype).permute(2, 0, 1).contiguous()
    y = ref.to(dtype).permute(2, 0, 1).contiguous()
    return _SSIMMean.apply(x, y, gaussian_window(window_size, sigma, dtype=dtype))


# ---- EWA projection --------------------------------------------------------------------------
class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, K, width, height, support_sigmas, near, blur,
                want_view):
        means2d, conics, depths, visible, means_cam, rot_cam = _ext().project_forward(
            means, quats, scales, viewmat, K, width, height, support_sigmas, near, blur,
            want_view, torch.get_num_threads())
        ctx.save_for_backward(means, quats, scales, viewmat, K)
        ctx.meta = (width, height, support_sigmas, near, blur)
        ctx.mark_non_differentiable(visible)
        return means2d, conics, depths, visible, means_cam, rot_cam

    @staticmethod
    @once_differentiable
    def backward(ctx, v_means2d, v_conics, v_depths, _v_visible, v_means_cam, v_rot_cam):
        means, quats, scales, viewmat, K = ctx.saved_tensors
        width, height, support_sigmas, near, blur = ctx.meta

        def dense(v, shape):
            return torch.zeros(shape, dtype=means.dtype) if v is None else v.to(means.dtype).contiguous()

        def optional(v):  # an unused output: an empty tensor tells the kernel to skip it
            return means.new_zeros(0) if v is None or v.numel() == 0 else v.to(means.dtype).contiguous()

        n = means.shape[0]
        v_means, v_quats, v_scales = _ext().project_backward(
            means, quats, scales, viewmat, K, width, height, support_sigmas, near, blur,
            dense(v_means2d, (n, 2)), dense(v_conics, (n, 3)), dense(v_depths, (n,)),
            optional(v_means_cam), optional(v_rot_cam), torch.get_num_threads())
        return v_means, v_quats, v_scales, None, None, None, None, None, None, None, None


def project_ellipsoids_fused(means, quats, scales, world_to_cam, K, width, height,
                             support_sigmas: float = 3.0, near: float = 0.01, blur: float = 0.3,
                             want_view: bool = False):
    """(means2d [N, 2], conics [N, 3], depths [N], visible [N] bool, means_cam, rotmats_cam)
    exactly as ``functional.projection.project_ellipsoids`` computes them; differentiable in
    means, quats and scales. means_cam [N, 3] and rotmats_cam [N, 3, 3] (the learned kernel's
    inputs) are filled only with ``want_view``, else empty."""
    dtype = torch.float64 if torch.float64 in (means.dtype, quats.dtype, scales.dtype) else torch.float32
    return _Project.apply(
        means.to(dtype).contiguous(), quats.to(dtype).contiguous(), scales.to(dtype).contiguous(),
        world_to_cam.detach().double().cpu(), K.detach().double().cpu(), int(width), int(height),
        float(support_sigmas), float(near), float(blur), bool(want_view),
    )


# ---- spherical harmonics -----------------------------------------------------------------------
class _SHColor(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sh0, sh_rest, dirs, degree):
        rgb = _ext().sh_forward(sh0, sh_rest, dirs, degree, torch.get_num_threads())
        ctx.save_for_backward(sh0, sh_rest, dirs)
        ctx.degree = degree
        return rgb

    @staticmethod
    @once_differentiable
    def backward(ctx, v_rgb):
        sh0, sh_rest, dirs = ctx.saved_tensors
        v0, vr, vd = _ext().sh_backward(sh0, sh_rest, dirs, ctx.degree, v_rgb.to(dirs.dtype).contiguous(),
                                        ctx.needs_input_grad[2], torch.get_num_threads())
        return v0, vr, (vd if ctx.needs_input_grad[2] else None), None


def eval_sh_fused(sh0: torch.Tensor, sh_rest: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """``functional.sh.eval_sh`` of cat([sh0, sh_rest], 1) without building the concatenation.

    sh0 [N, 1, 3], sh_rest [N, B, 3] (bands above ``degree`` ignored), dirs [N, 3] -> rgb [N, 3].
    """
    dtype = torch.float64 if torch.float64 in (sh0.dtype, sh_rest.dtype, dirs.dtype) else torch.float32
    return _SHColor.apply(sh0.to(dtype).contiguous(), sh_rest.to(dtype).contiguous(),
                          dirs.to(dtype).contiguous(), int(degree))


# ---- the learned kernel around Phi_proj (renders without gradients) ----------------------------
def learned_encode_fused(z3d, means_cam, scales, rotmats_cam, use_mu: bool, use_s: bool, use_R: bool,
                         dist_scale: float, angle_shift: float, angle_scale: float) -> torch.Tensor:
    """``LearnedKernel.encode`` in one native pass: [M, D] Phi_proj inputs. No gradients."""
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad
                                       for t in (z3d, means_cam, scales, rotmats_cam)):
        raise RuntimeError("learned_encode_fused has no backward; call it under torch.no_grad()")
    c = lambda t: None if t is None else t.float().contiguous()  # noqa: E731
    return _ext().learned_encode(c(z3d), c(means_cam), c(scales), c(rotmats_cam), use_mu, use_s, use_R,
                                 dist_scale, angle_shift, angle_scale, torch.get_num_threads())


def learned_decode_fused(z2d, layers, radii2, slope: float) -> torch.Tensor:
    """``LearnedKernel.decode`` (with the sigmoid) in one native pass: [M, P]. ``layers`` are
    Phi_dec's three ``nn.Linear``. No gradients."""
    if torch.is_grad_enabled() and (z2d.requires_grad or any(p.requires_grad for l in layers for p in l.parameters())):
        raise RuntimeError("learned_decode_fused has no backward; call it under torch.no_grad()")
    (w1, b1), (w2, b2), (w3, b3) = [(l.weight.detach().float().contiguous(), l.bias.detach().float().contiguous())
                                    for l in layers]
    return _ext().learned_decode(z2d.float().contiguous(), w1, b1, w2, b2, w3, b3,
                                 radii2.float().contiguous(), slope, torch.get_num_threads())


def bf16_mlp_available() -> bool:
    """Whether the native build has :func:`learned_profile_fused` (AVX-512 BF16 at build time)."""
    ext = cpu_native.load_extension()
    return ext is not None and bool(ext.has_bf16_mlp())


def learned_profile_fused(z3d, means_cam, scales, rotmats_cam, use_mu: bool, use_s: bool, use_R: bool,
                          dist_scale: float, angle_shift: float, angle_scale: float,
                          proj_layers, dec_layers, radii2, slope: float) -> torch.Tensor:
    """``LearnedKernel.profile`` with Phi_proj in bf16 (what CPU autocast computes), in one
    native pass: encode -> Phi_proj -> Phi_dec at ``radii2``: [M, P]. ``proj_layers`` are
    Phi_proj's ``nn.Linear`` (leaky ReLU between them), ``dec_layers`` Phi_dec's three.
    No gradients."""
    params = [p for l in (*proj_layers, *dec_layers) for p in l.parameters()]
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad
                                       for t in (z3d, means_cam, scales, rotmats_cam, *params)):
        raise RuntimeError("learned_profile_fused has no backward; call it under torch.no_grad()")
    c = lambda t: None if t is None else t.detach().float().contiguous()  # noqa: E731
    (w1, b1), (w2, b2), (w3, b3) = [(c(l.weight), c(l.bias)) for l in dec_layers]
    return _ext().learned_profile(c(z3d), c(means_cam), c(scales), c(rotmats_cam), use_mu, use_s, use_R,
                                  dist_scale, angle_shift, angle_scale,
                                  [c(l.weight) for l in proj_layers], [c(l.bias) for l in proj_layers],
                                  w1, b1, w2, b2, w3, b3, c(radii2), slope, torch.get_num_threads())
