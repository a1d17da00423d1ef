"""Native CPU renderer for 2D image splats (``csrc/image_splat.cpp``), used by `splatk image`.

Renders the plain sum ``I(x) = sum_i c_i k_i(u, v)`` of :class:`splatk.image.model.Splats2D`
from its transformed parameters (pixel means, Cholesky factors, colours, the kernel's per-splat
values) and each splat's pixel box, with the torch path's semantics; gradients flow back to
those four tensors, and from there through autograd to the raw parameters. The torch path of
``Splats2D.render`` is the reference it is tested against (tests/backends/test_image_cpu.py).
"""
from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

#: kernel codes of image_splat.cpp
KIND_CODES = {"gaussian": 0, "gabor": 1, "table": 2}


class _ImageSplatsCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, chol, colors, extras, bbox, kind, aux, width, height):
        from .cpu_native import load_extension

        means, chol, colors, extras = (t.contiguous() for t in (means, chol, colors, extras))
        img = load_extension().image_forward(means, chol, colors, extras, bbox, kind, aux, width, height,
                                             torch.get_num_threads())
        ctx.save_for_backward(means, chol, colors, extras, bbox)
        ctx.kind, ctx.aux = kind, aux
        return img

    @staticmethod
    @once_differentiable
    def backward(ctx, v_img):
        from .cpu_native import load_extension

        means, chol, colors, extras, bbox = ctx.saved_tensors
        v_means, v_chol, v_colors, v_extras = load_extension().image_backward(
            means, chol, colors, extras, bbox, ctx.kind, ctx.aux, v_img.contiguous(), torch.get_num_threads())
        return v_means, v_chol, v_colors, v_extras, None, None, None, None, None


def render_image_splats_cpu(means: torch.Tensor, chol: torch.Tensor, colors: torch.Tensor,
                            extras: torch.Tensor, bbox: torch.Tensor, kind: str, aux: int,
                            width: int, height: int) -> torch.Tensor:
    """[H, W, 3] sum of the splats.

    Args:
        means: [N, 2] pixel means (x, y); pixel centres sit at integer + 0.5.
        chol: [N, 3] l11, l21, l22 of the covariance's Cholesky factor (pixels, diagonal > 0).
        colors: [N, 3].
        extras: [N, E]: nothing for ``gaussian`` (E = 0); for ``gabor`` the amplitudes [2, K]
            then the frequencies [2, K] (E = 4 K); for ``table`` the [G, G] table (E = G * G).
        bbox: int32 [N, 4] pixel boxes (x0, y0, x1, y1), ends exclusive; may reach outside.
        kind: gaussian | gabor | table.
        aux: K for gabor, G for table, else 0.
    """
    if kind not in KIND_CODES:
        raise ValueError(f"unknown image kernel {kind!r}; choose from {', '.join(KIND_CODES)}")
    return _ImageSplatsCPU.apply(means, chol, colors, extras, bbox, KIND_CODES[kind], int(aux),
                                 int(width), int(height))
