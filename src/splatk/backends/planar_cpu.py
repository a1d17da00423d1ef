"""Native CPU rasteriser for planar primitives (``csrc/planar_raster.cpp``).

Same signature and semantics as the dense reference
:func:`splatk.backends.planar_torch.rasterize_planar`. Torch does the per-splat work (which
splats are drawn and their homographies M, :func:`~splatk.backends.planar_torch.planar_visible`;
their pixel bounding boxes); the native op composites 16x16 tiles and returns gradients with
respect to M, opacities, colours, grid tables and the background. Gradients reach means, quats
and scales through autograd of :func:`~splatk.backends.planar_torch.splat_homographies`.
"""
from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from .types import RasterOutput
from .planar_torch import planar_visible
from .types import PlanarProfile

_KIND_CODES = {"gaussian_surfel": 0, "grid": 1}


#: pixels of slack on each side of the exact box: float rounding of (u, v) in the rasteriser
#: never reaches it, so no pixel the reference draws is dropped
BBOX_SLACK = 1e-3


def planar_bboxes(M: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """int32 [m, 4] pixel boxes (x0, x1, y0, y1), half-open and clipped, holding every pixel
    whose centre lies in the image of the splat's 3-sigma disk.

    The disk u^2 + v^2 <= 9 is the conic Q = diag(1, 1, -9) in (u, v, 1); its image under M has
    the dual conic C* = M Q^-1 M^T (tangent lines l satisfy l^T C* l = 0), so its vertical
    tangents x = c, l = (1, 0, -c), solve C*_22 c^2 - 2 C*_02 c + C*_00 = 0 (and the same for y)
    (the exact bounding box, as 2DGS computes it). Valid for splats from ``planar_visible``: the
    whole disk is in front of the camera, so its image is an ellipse and C*_22 < 0.
    Computed in float64 from the M the rasteriser uses.
    """
    Md = M.detach().double()
    q_inv = torch.tensor([1.0, 1.0, -1.0 / 9.0], dtype=torch.float64, device=M.device)
    C = (Md * q_inv) @ Md.transpose(1, 2)  # [m, 3, 3] dual conic

    def extent(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor, size: int):
        # roots of c t^2 - 2 b t + a = 0; pixel i is inside when its centre i + 0.5 is in [lo, hi]
        d = (b * b - a * c).clamp_min(0).sqrt()
        r1, r2 = (b - d) / c, (b + d) / c
        lo, hi = torch.minimum(r1, r2), torch.maximum(r1, r2)
        i0 = torch.ceil(lo - 0.5 - BBOX_SLACK).clamp(0, size)
        i1 = (torch.floor(hi - 0.5 + BBOX_SLACK) + 1).clamp(0, size)
        return i0, torch.maximum(i1, i0)

    x0, x1 = extent(C[:, 0, 0], C[:, 0, 2], C[:, 2, 2], width)
    y0, y1 = extent(C[:, 1, 1], C[:, 1, 2], C[:, 2, 2], height)
    return torch.stack([x0, x1, y0, y1], 1).to(torch.int32).contiguous()


class _PlanarRasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, M, opacities, colors, table, background, bbox, kind, width, height):
        from .cpu_native import load_extension

        img, alpha, *state = load_extension().planar_forward(
            M, bbox, opacities, colors, table, kind, width, height, background,
            torch.get_num_threads(),
        )
        ctx.save_for_backward(M, bbox, opacities, colors, table, background, *state)
        ctx.meta = (kind, width, height)
        return img, alpha

    @staticmethod
    @once_differentiable
    def backward(ctx, v_img, v_alpha):
        from .cpu_native import load_extension

        M, bbox, opacities, colors, table, background, *state = ctx.saved_tensors
        kind, width, height = ctx.meta
        dtype = colors.dtype
        v_img = v_img.to(dtype).contiguous()
        v_alpha = v_alpha.to(dtype).contiguous()
        v_M, v_op, v_col, v_tab = load_extension().planar_backward(
            M, bbox, opacities, colors, table, kind, width, height, background, list(state), v_img,
            v_alpha, torch.get_num_threads(),
        )
        T_final = state[0]
        v_bg = (T_final[..., None] * v_img).sum((0, 1))
        v_tab = v_tab.reshape(table.shape) if kind == _KIND_CODES["grid"] else None
        return v_M, v_op, v_col, v_tab, v_bg, None, None, None, None


def rasterize_planar_cpu(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                         opacities: torch.Tensor, colors: torch.Tensor, viewmat: torch.Tensor,
                         K: torch.Tensor, width: int, height: int, profile: PlanarProfile,
                         background: torch.Tensor | None = None) -> RasterOutput:
    """Native planar rasteriser (CPU tensors, float32 or float64); see the module docstring."""
    from ..errors import BackendUnavailable
    from .cpu_native import load_extension, unavailable_reason

    if load_extension() is None:
        raise BackendUnavailable(f"backend 'cpu' is not available here ({unavailable_reason()})")
    if profile.kind not in _KIND_CODES:
        raise ValueError(f"unknown planar profile {profile.kind!r}; choose from {', '.join(_KIND_CODES)}")
    if profile.kind == "grid" and (profile.table is None or profile.table.dim() != 3):
        raise ValueError("planar profile 'grid' needs a table [N, G, G]")
    tensors = [means, quats, scales, opacities, colors, viewmat, K]
    if any(t.device.type != "cpu" for t in tensors):
        raise ValueError("planar backend 'cpu' needs CPU tensors; use backend='torch'")
    dtype = torch.float64 if any(t.dtype == torch.float64 for t in tensors) else torch.float32
    channels = colors.shape[1]
    if background is None:
        background = torch.zeros(channels, dtype=dtype)
    order, M = planar_visible(means, quats, scales, viewmat, K)
    bbox = planar_bboxes(M, int(width), int(height))
    if profile.kind == "grid":
        table = profile.table.index_select(0, order).to(dtype).contiguous()
    else:
        table = torch.zeros(0, dtype=dtype)
    img, alpha = _PlanarRasterizeCPU.apply(
        M.reshape(-1, 9).to(dtype).contiguous(),
        opacities.reshape(-1).index_select(0, order).to(dtype).contiguous(),
        colors.index_select(0, order).to(dtype).contiguous(),
        table,
        background.reshape(-1).to(dtype).contiguous(),
        bbox,
        _KIND_CODES[profile.kind],
        int(width),
        int(height),
    )
    return RasterOutput(img, alpha)
