"""Image splats in Triton: the plain sum ``I(x) = sum_i c_i k_i(u, v)`` of 2D splats (`splatk
image`), forward and backward, one program per 16x16 tile.

Same inputs and semantics as the native cpu op (:mod:`.image_cpu`) and the torch path of the
image model, which is the reference: pixel means, Cholesky factors (l11, l21, l22), colours, the
kernel's per-splat values (``extras``) and each splat's pixel box. For pixel centre p,
``(u, v) = L^-1 (p - mu) / 3`` by forward substitution; the envelope is ``exp(-4.5 r2)`` inside
the unit disk (0 outside, and outside the splat's box); ``gabor`` multiplies it by two sums of
``K`` cosine waves (amplitudes then frequencies in ``extras``), ``table`` by a bilinear lookup in
a ``G x G`` table. Gradients: means, Cholesky factors, colours and ``extras``.
"""
from __future__ import annotations

import torch
import triton
import triton.language as tl

from .triton_binning import bin_boxes
from .triton_raster import pixel_block
from .types import TILE_SIZE

KIND_CODES = {"gaussian": 0, "gabor": 1, "table": 2}


@triton.jit
def _local(g, px, py, means_ptr, chol_ptr, bbox_ptr, width, height):
    """(u, v) normalised to the 3-sigma disk, the pixels that count, and what the backward needs."""
    mx = tl.load(means_ptr + 2 * g)
    my = tl.load(means_ptr + 2 * g + 1)
    l11 = tl.load(chol_ptr + 3 * g)
    l21 = tl.load(chol_ptr + 3 * g + 1)
    l22 = tl.load(chol_ptr + 3 * g + 2)
    bx0 = tl.load(bbox_ptr + 4 * g)
    by0 = tl.load(bbox_ptr + 4 * g + 1)
    bx1 = tl.load(bbox_ptr + 4 * g + 2)
    by1 = tl.load(bbox_ptr + 4 * g + 3)
    dx = (px.to(tl.float32) + 0.5) - mx
    dy = (py.to(tl.float32) + 0.5) - my
    # IEEE divisions (Triton's default one may be approximate): the torch path's rounding, so
    # a pixel on the support's edge is inside or outside in both alike
    u = tl.div_rn(dx, l11)
    v = tl.div_rn(dy - l21 * u, l22)
    un = u * (1.0 / 3.0)
    vn = v * (1.0 / 3.0)
    r2 = un * un + vn * vn
    inside = ((px >= bx0) & (px < bx1) & (py >= by0) & (py < by1) & (px < width) & (py < height)
              & (r2 <= 1.0))
    return u, v, un, vn, l11, l21, l22, inside


@triton.jit
def _waves(x, g, extras_ptr, E, d: tl.constexpr, AUX: tl.constexpr):
    """sum_j a_dj cos(pi f_dj x) of splat g along axis d (amplitudes, then frequencies)."""
    total = tl.zeros_like(x)
    for j in tl.static_range(AUX):
        a = tl.load(extras_ptr + g * E + d * AUX + j)
        f = tl.load(extras_ptr + g * E + 2 * AUX + d * AUX + j)
        total += a * tl.cos((3.141592653589793 * f) * x)
    return total


@triton.jit
def _table_coords(x, G: tl.constexpr):
    t = (tl.minimum(tl.maximum(x, -1.0), 1.0) + 1.0) * 0.5 * (G - 1)
    i = tl.minimum(tl.maximum(t.to(tl.int32), 0), G - 2)
    return i, t - i.to(tl.float32)


@triton.jit
def _table_corners(un, vn, g, extras_ptr, E, inside, AUX: tl.constexpr):
    """The four table entries around (un, vn), their flat index and the bilinear weights."""
    iu, fu = _table_coords(un, AUX)
    iv, fv = _table_coords(vn, AUX)
    base = g * E + iv * AUX + iu
    t00 = tl.load(extras_ptr + base, mask=inside, other=0.0)
    t01 = tl.load(extras_ptr + base + 1, mask=inside, other=0.0)
    t10 = tl.load(extras_ptr + base + AUX, mask=inside, other=0.0)
    t11 = tl.load(extras_ptr + base + AUX + 1, mask=inside, other=0.0)
    return base, fu, fv, t00, t01, t10, t11


@triton.jit
def _value(un, vn, g, extras_ptr, E, inside, KIND: tl.constexpr, AUX: tl.constexpr):
    env = tl.exp(-4.5 * (un * un + vn * vn))
    if KIND == 0:
        w = env
    elif KIND == 1:
        w = env * _waves(un, g, extras_ptr, E, 0, AUX) * _waves(vn, g, extras_ptr, E, 1, AUX)
    else:
        base, fu, fv, t00, t01, t10, t11 = _table_corners(un, vn, g, extras_ptr, E, inside, AUX)
        w = env * ((t00 * (1.0 - fu) + t01 * fu) * (1.0 - fv) + (t10 * (1.0 - fu) + t11 * fu) * fv)
    return tl.where(inside, w, 0.0), env


@triton.jit
def image_fwd_kernel(means_ptr, chol_ptr, colors_ptr, extras_ptr, bbox_ptr, tile_offsets_ptr, flat_ids_ptr,
                     out_ptr, width, height, tiles_x, E,
                     KIND: tl.constexpr, AUX: tl.constexpr, TILE: tl.constexpr):
    tile = tl.program_id(0)
    px, py, _ = pixel_block(tile, tiles_x, width, height, TILE)
    ch = tl.arange(0, 4)
    acc = tl.zeros([TILE * TILE, 4], tl.float32)
    start = tl.load(tile_offsets_ptr + tile)
    end = tl.load(tile_offsets_ptr + tile + 1)
    for i in range(start, end):
        g = tl.load(flat_ids_ptr + i)
        u, v, un, vn, l11, l21, l22, inside = _local(g, px, py, means_ptr, chol_ptr, bbox_ptr, width, height)
        w, env = _value(un, vn, g, extras_ptr, E, inside, KIND, AUX)
        col = tl.load(colors_ptr + 3 * g + ch, mask=ch < 3, other=0.0)
        acc += w[:, None] * col[None, :]
    in_img = (px < width) & (py < height)
    tl.store(out_ptr + (py * width + px)[:, None] * 3 + ch[None, :], acc, mask=in_img[:, None] & (ch < 3)[None, :])


@triton.jit
def image_bwd_kernel(means_ptr, chol_ptr, colors_ptr, extras_ptr, bbox_ptr, tile_offsets_ptr, flat_ids_ptr,
                     v_out_ptr, g_means_ptr, g_chol_ptr, g_colors_ptr, g_extras_ptr, width, height, tiles_x, E,
                     KIND: tl.constexpr, AUX: tl.constexpr, TILE: tl.constexpr):
    tile = tl.program_id(0)
    px, py, in_img = pixel_block(tile, tiles_x, width, height, TILE)
    ch = tl.arange(0, 4)
    v_out = tl.load(v_out_ptr + (py * width + px)[:, None] * 3 + ch[None, :],
                    mask=in_img[:, None] & (ch < 3)[None, :], other=0.0)
    start = tl.load(tile_offsets_ptr + tile)
    end = tl.load(tile_offsets_ptr + tile + 1)
    for i in range(start, end):
        g = tl.load(flat_ids_ptr + i)
        u, v, un, vn, l11, l21, l22, inside = _local(g, px, py, means_ptr, chol_ptr, bbox_ptr, width, height)
        w, env = _value(un, vn, g, extras_ptr, E, inside, KIND, AUX)
        col = tl.load(colors_ptr + 3 * g + ch, mask=ch < 3, other=0.0)
        tl.atomic_add(g_colors_ptr + 3 * g + ch, tl.sum(w[:, None] * v_out, axis=0), mask=ch < 3)
        v_w = tl.where(inside, tl.sum(v_out * col[None, :], axis=1), 0.0)
        # w = env * S: the envelope's share, then S's own
        if KIND == 0:
            v_env = v_w
            v_un = tl.zeros_like(un)
            v_vn = tl.zeros_like(vn)
        elif KIND == 1:
            w0 = _waves(un, g, extras_ptr, E, 0, AUX)
            w1 = _waves(vn, g, extras_ptr, E, 1, AUX)
            v_env = v_w * w0 * w1
            v_w0 = v_w * env * w1
            v_w1 = v_w * env * w0
            v_un = tl.zeros_like(un)
            v_vn = tl.zeros_like(vn)
            for j in tl.static_range(AUX):
                a0 = tl.load(extras_ptr + g * E + j)
                a1 = tl.load(extras_ptr + g * E + AUX + j)
                f0 = tl.load(extras_ptr + g * E + 2 * AUX + j)
                f1 = tl.load(extras_ptr + g * E + 3 * AUX + j)
                ph0 = (3.141592653589793 * f0) * un
                ph1 = (3.141592653589793 * f1) * vn
                s0 = tl.sin(ph0)
                s1 = tl.sin(ph1)
                tl.atomic_add(g_extras_ptr + g * E + j, tl.sum(v_w0 * tl.cos(ph0), axis=0))
                tl.atomic_add(g_extras_ptr + g * E + AUX + j, tl.sum(v_w1 * tl.cos(ph1), axis=0))
                tl.atomic_add(g_extras_ptr + g * E + 2 * AUX + j,
                              tl.sum(v_w0 * a0 * -s0 * 3.141592653589793 * un, axis=0))
                tl.atomic_add(g_extras_ptr + g * E + 3 * AUX + j,
                              tl.sum(v_w1 * a1 * -s1 * 3.141592653589793 * vn, axis=0))
                v_un += v_w0 * a0 * -s0 * 3.141592653589793 * f0
                v_vn += v_w1 * a1 * -s1 * 3.141592653589793 * f1
        else:
            base, fu, fv, t00, t01, t10, t11 = _table_corners(un, vn, g, extras_ptr, E, inside, AUX)
            v_env = v_w * ((t00 * (1.0 - fu) + t01 * fu) * (1.0 - fv) + (t10 * (1.0 - fu) + t11 * fu) * fv)
            v_s = v_w * env
            tl.atomic_add(g_extras_ptr + base, v_s * (1.0 - fu) * (1.0 - fv), mask=inside)
            tl.atomic_add(g_extras_ptr + base + 1, v_s * fu * (1.0 - fv), mask=inside)
            tl.atomic_add(g_extras_ptr + base + AUX, v_s * (1.0 - fu) * fv, mask=inside)
            tl.atomic_add(g_extras_ptr + base + AUX + 1, v_s * fu * fv, mask=inside)
            # the clamp to [-1, 1] passes gradient inside it, edges included (torch.clamp)
            du = tl.where((un >= -1.0) & (un <= 1.0), 0.5 * (AUX - 1), 0.0)
            dv = tl.where((vn >= -1.0) & (vn <= 1.0), 0.5 * (AUX - 1), 0.0)
            v_un = v_s * ((t01 - t00) * (1.0 - fv) + (t11 - t10) * fv) * du
            v_vn = v_s * ((t10 - t00) * (1.0 - fu) + (t11 - t01) * fu) * dv
        v_r2 = v_env * -4.5 * env
        v_u = (v_un + v_r2 * 2.0 * un) * (1.0 / 3.0)
        v_v = (v_vn + v_r2 * 2.0 * vn) * (1.0 / 3.0)
        # v = (dy - l21 u) / l22, u = dx / l11
        v_dy = v_v / l22
        v_l21 = -v_v * u / l22
        v_l22 = -v_v * v / l22
        v_u = v_u - v_v * l21 / l22
        v_dx = v_u / l11
        v_l11 = -v_u * u / l11
        tl.atomic_add(g_means_ptr + 2 * g, tl.sum(tl.where(inside, -v_dx, 0.0), axis=0))
        tl.atomic_add(g_means_ptr + 2 * g + 1, tl.sum(tl.where(inside, -v_dy, 0.0), axis=0))
        tl.atomic_add(g_chol_ptr + 3 * g, tl.sum(tl.where(inside, v_l11, 0.0), axis=0))
        tl.atomic_add(g_chol_ptr + 3 * g + 1, tl.sum(tl.where(inside, v_l21, 0.0), axis=0))
        tl.atomic_add(g_chol_ptr + 3 * g + 2, tl.sum(tl.where(inside, v_l22, 0.0), axis=0))


class _TritonImageSplats(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, chol, colors, extras, bbox, kind, aux, width, height):
        means, chol, colors, extras = (t.detach().contiguous() for t in (means, chol, colors, extras))
        bbox = bbox.to(torch.int32).contiguous()
        n = means.shape[0]
        b = bbox.long()
        ranks = torch.arange(n, device=means.device)
        flat_ids, tile_offsets, tiles_x = bin_boxes(b[:, 0].clamp(0, width), b[:, 2].clamp(0, width),
                                                    b[:, 1].clamp(0, height), b[:, 3].clamp(0, height),
                                                    ranks, ranks, width, height)
        out = torch.zeros(height * width, 3, device=means.device, dtype=torch.float32)
        image_fwd_kernel[(tile_offsets.numel() - 1,)](
            means, chol, colors, extras, bbox, tile_offsets, flat_ids, out, width, height, tiles_x,
            extras.shape[1], KIND=kind, AUX=aux, TILE=TILE_SIZE, enable_fp_fusion=False)
        ctx.save_for_backward(means, chol, colors, extras, bbox, tile_offsets, flat_ids)
        ctx.meta = (kind, aux, width, height, tiles_x)
        return out.view(height, width, 3)

    @staticmethod
    def backward(ctx, v_out):
        means, chol, colors, extras, bbox, tile_offsets, flat_ids = ctx.saved_tensors
        kind, aux, width, height, tiles_x = ctx.meta
        grads = [torch.zeros_like(t) for t in (means, chol, colors, extras)]
        image_bwd_kernel[(tile_offsets.numel() - 1,)](
            means, chol, colors, extras, bbox, tile_offsets, flat_ids, v_out.contiguous(), *grads,
            width, height, tiles_x, extras.shape[1], KIND=kind, AUX=aux, TILE=TILE_SIZE, enable_fp_fusion=False)
        return (*grads, None, None, None, None, None)


def render_image_splats_triton(means, chol, colors, extras, bbox, kind: str, aux: int, width: int,
                               height: int) -> torch.Tensor:
    """[H, W, 3] sum of the splats; the arguments of ``Backend.render_image_splats``. The kernels
    compute in float32 (other float inputs are rendered in float32 and the image cast back)."""
    if kind not in KIND_CODES:
        raise ValueError(f"unknown image kernel {kind!r}; choose from {', '.join(KIND_CODES)}")
    # K waves (gabor) or G (table) are compiled in; the gaussian has none
    aux = int(aux) if kind != "gaussian" else 1
    if kind == "table" and (aux < 2 or extras.shape[1] != aux * aux):
        raise ValueError(f"table extras must be [N, G * G] with G >= 2, got {tuple(extras.shape)} for G = {aux}")
    dtype = means.dtype
    means, chol, colors, extras = (t.float() for t in (means, chol, colors, extras))
    img = _TritonImageSplats.apply(means, chol, colors, extras, bbox, KIND_CODES[kind], aux, int(width),
                                   int(height))
    return img.to(dtype)
