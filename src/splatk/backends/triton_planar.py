"""Planar (surfel) rasteriser in Triton: forward and backward kernels, one program per 16x16 tile.

Same contract as :func:`splatk.backends.planar_torch.rasterize_planar`. As in the native cpu
version (:mod:`.planar_cpu`), torch does the per-splat work on the device (which splats are
drawn, in depth order, and their homographies M: :func:`~.planar_torch.planar_visible`; their
pixel boxes: :func:`~.planar_cpu.planar_bboxes`); the kernels intersect each pixel's ray with
the splat's plane (2DGS Eq. 9-10), composite front to back and return gradients with respect
to M, opacities, colours, grid tables and the background. Gradients reach means, quats and
scales through autograd of the homographies.
"""
from __future__ import annotations

import torch
import triton
import triton.language as tl

from .planar_cpu import planar_bboxes
from .planar_torch import planar_visible
from .triton_binning import bin_boxes
from .triton_raster import composite_backward_start, composite_backward_step, composite_forward_step, pixel_block
from .types import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE_SIZE, PlanarProfile, RasterOutput

KIND_CODES = {"gaussian_surfel": 0, "grid": 1}
#: exp(-S^2 r2 / 2) with the surfel's support at S = 3 sigma
_SURFEL_HALF_S2 = 4.5


@triton.jit
def _uv(g, px, py, M_ptr):
    """(u, v) where pixel centres' rays meet splat g's plane, normalised so the support is the
    unit disk, with the intermediates the backward needs. Rounds as ``ray_splat_uv`` (with fused
    multiply-adds off, see :func:`_constants`), so a pixel on a disk's edge is drawn alike."""
    m00 = tl.load(M_ptr + 9 * g)
    m01 = tl.load(M_ptr + 9 * g + 1)
    m02 = tl.load(M_ptr + 9 * g + 2)
    m10 = tl.load(M_ptr + 9 * g + 3)
    m11 = tl.load(M_ptr + 9 * g + 4)
    m12 = tl.load(M_ptr + 9 * g + 5)
    m20 = tl.load(M_ptr + 9 * g + 6)
    m21 = tl.load(M_ptr + 9 * g + 7)
    m22 = tl.load(M_ptr + 9 * g + 8)
    x = px.to(tl.float32) + 0.5
    y = py.to(tl.float32) + 0.5
    hu0 = -m00 + x * m20
    hu1 = -m01 + x * m21
    hu2 = -m02 + x * m22
    hv0 = -m10 + y * m20
    hv1 = -m11 + y * m21
    hv2 = -m12 + y * m22
    c0 = hu1 * hv2 - hu2 * hv1
    c1 = hu2 * hv0 - hu0 * hv2
    c2 = hu0 * hv1 - hu1 * hv0
    # IEEE divisions (Triton's default one may be approximate), as torch's
    big_u = tl.div_rn(c0, c2)
    big_v = tl.div_rn(c1, c2)
    return (tl.div_rn(big_u, 3.0), tl.div_rn(big_v, 3.0), big_u, big_v, c2, x, y, hu0, hu1, hu2, hv0, hv1,
            hv2)


@triton.jit
def _grid_coords(u, v, G: tl.constexpr):
    tu = (tl.minimum(tl.maximum(u, -1.0), 1.0) + 1.0) * 0.5 * (G - 1)
    tv = (tl.minimum(tl.maximum(v, -1.0), 1.0) + 1.0) * 0.5 * (G - 1)
    iu = tl.minimum(tl.maximum(tu.to(tl.int32), 0), G - 2)
    iv = tl.minimum(tl.maximum(tv.to(tl.int32), 0), G - 2)
    return iu, iv, tu - iu.to(tl.float32), tv - iv.to(tl.float32)


@triton.jit
def _kernel_value(u, v, g, table_ptr, inside, KIND: tl.constexpr, G: tl.constexpr, HALF_S2: tl.constexpr):
    r2 = u * u + v * v
    if KIND == 0:
        k = tl.exp(-HALF_S2 * r2)
    else:
        iu, iv, fu, fv = _grid_coords(u, v, G)
        base = g * (G * G) + iv * G + iu
        t00 = tl.load(table_ptr + base, mask=inside, other=0.0)
        t01 = tl.load(table_ptr + base + 1, mask=inside, other=0.0)
        t10 = tl.load(table_ptr + base + G, mask=inside, other=0.0)
        t11 = tl.load(table_ptr + base + G + 1, mask=inside, other=0.0)
        k = (t00 * (1.0 - fu) + t01 * fu) * (1.0 - fv) + (t10 * (1.0 - fu) + t11 * fu) * fv
    return tl.where(inside, k, 0.0)


@triton.jit
def planar_fwd_kernel(
    M_ptr, opac_ptr, colors_ptr, table_ptr, bg_ptr, tile_offsets_ptr, flat_ids_ptr,
    out_img_ptr, out_tfinal_ptr, out_ncontrib_ptr, width, height, tiles_x, C,
    KIND: tl.constexpr, G: tl.constexpr, CP: tl.constexpr, TILE: tl.constexpr, HALF_S2: tl.constexpr,
    A_MAX: tl.constexpr, A_MIN: tl.constexpr, T_STOP: tl.constexpr,
):
    tile = tl.program_id(0)
    px, py, in_img = pixel_block(tile, tiles_x, width, height, TILE)
    ch = tl.arange(0, CP)
    ch_ok = ch < C
    start = tl.load(tile_offsets_ptr + tile)
    end = tl.load(tile_offsets_ptr + tile + 1)

    T = tl.full([TILE * TILE], 1.0, tl.float32)
    acc = tl.zeros([TILE * TILE, CP], tl.float32)
    alive = in_img
    n_contrib = tl.zeros([TILE * TILE], tl.int32)
    i = start
    any_alive = tl.max(alive.to(tl.int32), axis=0)
    while (i < end) & (any_alive > 0):
        g = tl.load(flat_ids_ptr + i)
        u, v, bu, bv, c2, x, y, hu0, hu1, hu2, hv0, hv1, hv2 = _uv(g, px, py, M_ptr)
        inside = (u * u + v * v) <= 1.0
        k = _kernel_value(u, v, g, table_ptr, inside, KIND, G, HALF_S2)
        T, acc, alive, n_contrib = composite_forward_step(
            k, inside, g, i - start + 1, T, acc, alive, n_contrib, opac_ptr, colors_ptr, ch, ch_ok, C,
            A_MAX, A_MIN, T_STOP)
        any_alive = tl.max(alive.to(tl.int32), axis=0)
        i += 1

    bg = tl.load(bg_ptr + ch, mask=ch_ok, other=0.0)
    pix = py * width + px
    tl.store(out_img_ptr + pix[:, None] * C + ch[None, :], acc + T[:, None] * bg[None, :],
             mask=in_img[:, None] & ch_ok[None, :])
    tl.store(out_tfinal_ptr + pix, T, mask=in_img)
    tl.store(out_ncontrib_ptr + pix, n_contrib, mask=in_img)


@triton.jit
def planar_bwd_kernel(
    M_ptr, opac_ptr, colors_ptr, table_ptr, bg_ptr, tile_offsets_ptr, flat_ids_ptr, tfinal_ptr,
    ncontrib_ptr, v_img_ptr, v_alpha_ptr, g_M_ptr, g_opac_ptr, g_colors_ptr, g_table_ptr,
    width, height, tiles_x, C,
    KIND: tl.constexpr, G: tl.constexpr, CP: tl.constexpr, TILE: tl.constexpr, HALF_S2: tl.constexpr,
    A_MAX: tl.constexpr, A_MIN: tl.constexpr,
):
    tile = tl.program_id(0)
    px, py, in_img = pixel_block(tile, tiles_x, width, height, TILE)
    pix = py * width + px
    ch = tl.arange(0, CP)
    ch_ok = ch < C
    start = tl.load(tile_offsets_ptr + tile)

    T, t_final, n_contrib, v_img, v_alpha, behind = composite_backward_start(
        pix, in_img, ch, ch_ok, C, tfinal_ptr, ncontrib_ptr, v_img_ptr, v_alpha_ptr, bg_ptr)
    last = tl.max(n_contrib, axis=0)
    for j in range(0, last):
        local = last - 1 - j
        g = tl.load(flat_ids_ptr + start + local)
        u, v, bu, bv, c2, x, y, hu0, hu1, hu2, hv0, hv1, hv2 = _uv(g, px, py, M_ptr)
        inside = (u * u + v * v) <= 1.0
        k = _kernel_value(u, v, g, table_ptr, inside, KIND, G, HALF_S2)
        T, behind, v_k, active = composite_backward_step(
            k, (local < n_contrib) & inside, g, T, behind, t_final, v_img, v_alpha, colors_ptr, g_colors_ptr,
            g_opac_ptr, opac_ptr, ch, ch_ok, C, A_MAX, A_MIN)
        if KIND == 0:
            v_r2 = v_k * (-HALF_S2) * k
            v_u = v_r2 * 2.0 * u
            v_v = v_r2 * 2.0 * v
        else:
            iu, iv, fu, fv = _grid_coords(u, v, G)
            base = g * (G * G) + iv * G + iu
            t00 = tl.load(table_ptr + base, mask=active, other=0.0)
            t01 = tl.load(table_ptr + base + 1, mask=active, other=0.0)
            t10 = tl.load(table_ptr + base + G, mask=active, other=0.0)
            t11 = tl.load(table_ptr + base + G + 1, mask=active, other=0.0)
            tl.atomic_add(g_table_ptr + base, v_k * (1.0 - fu) * (1.0 - fv), mask=active)
            tl.atomic_add(g_table_ptr + base + 1, v_k * fu * (1.0 - fv), mask=active)
            tl.atomic_add(g_table_ptr + base + G, v_k * (1.0 - fu) * fv, mask=active)
            tl.atomic_add(g_table_ptr + base + G + 1, v_k * fu * fv, mask=active)
            # the clamp to [-1, 1] passes gradient inside it (edges included, as torch.clamp)
            du = tl.where((u >= -1.0) & (u <= 1.0), 0.5 * (G - 1), 0.0)
            dv = tl.where((v >= -1.0) & (v <= 1.0), 0.5 * (G - 1), 0.0)
            v_u = v_k * ((t01 - t00) * (1.0 - fv) + (t11 - t10) * fv) * du
            v_v = v_k * ((t10 - t00) * (1.0 - fu) + (t11 - t01) * fu) * dv
        # (u, v) = (c0, c1) / c2 / 3 with c = h_u x h_v
        v_bu = v_u / 3.0
        v_bv = v_v / 3.0
        vc0 = v_bu / c2
        vc1 = v_bv / c2
        vc2 = -(v_bu * bu + v_bv * bv) / c2
        # d/dh_u = h_v x v_c, d/dh_v = v_c x h_u
        vhu0 = hv1 * vc2 - hv2 * vc1
        vhu1 = hv2 * vc0 - hv0 * vc2
        vhu2 = hv0 * vc1 - hv1 * vc0
        vhv0 = vc1 * hu2 - vc2 * hu1
        vhv1 = vc2 * hu0 - vc0 * hu2
        vhv2 = vc0 * hu1 - vc1 * hu0
        # h_u = -M0 + x M2, h_v = -M1 + y M2
        tl.atomic_add(g_M_ptr + 9 * g, tl.sum(tl.where(active, -vhu0, 0.0), axis=0))
        tl.atomic_add(g_M_ptr + 9 * g + 1, tl.sum(tl.where(active, -vhu1, 0.0), axis=0))
        tl.atomic_add(g_M_ptr + 9 * g + 2, tl.sum(tl.where(active, -vhu2, 0.0), axis=0))
        tl.atomic_add(g_M_ptr + 9 * g + 3, tl.sum(tl.where(active, -vhv0, 0.0), axis=0))
        tl.atomic_add(g_M_ptr + 9 * g + 4, tl.sum(tl.where(active, -vhv1, 0.0), axis=0))
        tl.atomic_add(g_M_ptr + 9 * g + 5, tl.sum(tl.where(active, -vhv2, 0.0), axis=0))
        tl.atomic_add(g_M_ptr + 9 * g + 6, tl.sum(tl.where(active, x * vhu0 + y * vhv0, 0.0), axis=0))
        tl.atomic_add(g_M_ptr + 9 * g + 7, tl.sum(tl.where(active, x * vhu1 + y * vhv1, 0.0), axis=0))
        tl.atomic_add(g_M_ptr + 9 * g + 8, tl.sum(tl.where(active, x * vhu2 + y * vhv2, 0.0), axis=0))


def _constants(kind: str, grid: int, channels: int) -> dict:
    # no fused multiply-adds: (u, v) rounds as the torch reference's, so a pixel on the disk's
    # edge is inside or outside in both alike
    return dict(KIND=KIND_CODES[kind], G=grid, CP=triton.next_power_of_2(max(channels, 1)), TILE=TILE_SIZE,
                HALF_S2=_SURFEL_HALF_S2, A_MAX=ALPHA_MAX, A_MIN=ALPHA_MIN, enable_fp_fusion=False)


class _TritonPlanar(torch.autograd.Function):
    """Gradients for M [m, 9], opacities, colours, the grid tables and the background."""

    @staticmethod
    def forward(ctx, M9, opacities, colors, table, background, kind, grid, width, height):
        device, m, channels = M9.device, M9.shape[0], colors.shape[1]
        M9, opacities, colors, table, background = (
            t.detach().contiguous() for t in (M9, opacities, colors, table, background))
        x0, x1, y0, y1 = planar_bboxes(M9.view(-1, 3, 3), width, height).long().unbind(1)
        ranks = torch.arange(m, device=device)  # planar_visible's order is front to back
        flat_ids, tile_offsets, tiles_x = bin_boxes(x0, x1, y0, y1, ranks, ranks, width, height)
        img = torch.empty(height * width, channels, device=device, dtype=torch.float32)
        t_final = torch.empty(height * width, device=device, dtype=torch.float32)
        n_contrib = torch.empty(height * width, device=device, dtype=torch.int32)
        planar_fwd_kernel[(tile_offsets.numel() - 1,)](
            M9, opacities, colors, table, background, tile_offsets, flat_ids, img, t_final, n_contrib,
            width, height, tiles_x, channels, T_STOP=T_MIN, **_constants(kind, grid, channels))
        ctx.save_for_backward(M9, opacities, colors, table, background, tile_offsets, flat_ids, t_final,
                              n_contrib)
        ctx.meta = (kind, grid, width, height, tiles_x)
        return img.view(height, width, channels), (1.0 - t_final).view(height, width, 1)

    @staticmethod
    def backward(ctx, v_img, v_alpha):
        M9, opacities, colors, table, background, tile_offsets, flat_ids, t_final, n_contrib = ctx.saved_tensors
        kind, grid, width, height, tiles_x = ctx.meta
        channels = colors.shape[1]
        v_img = v_img.contiguous().view(height * width, channels)
        v_alpha = v_alpha.contiguous().view(height * width)
        g_M, g_opac = torch.zeros_like(M9), torch.zeros_like(opacities)
        g_colors, g_table = torch.zeros_like(colors), torch.zeros_like(table)
        planar_bwd_kernel[(tile_offsets.numel() - 1,)](
            M9, opacities, colors, table, background, tile_offsets, flat_ids, t_final, n_contrib, v_img,
            v_alpha, g_M, g_opac, g_colors, g_table, width, height, tiles_x, channels,
            **_constants(kind, grid, channels))
        g_background = (v_img * t_final[:, None]).sum(0)
        return (g_M, g_opac, g_colors, g_table if ctx.needs_input_grad[3] else None, g_background,
                None, None, None, None)


def rasterize_planar_triton(means, quats, scales, opacities, colors, viewmat, K, width: int, height: int,
                            profile: PlanarProfile, background) -> RasterOutput:
    """The Triton planar rasteriser (float32); same contract and gradients as the torch one."""
    order, M = planar_visible(means, quats, scales, viewmat, K)
    if profile.kind == "grid":
        table = profile.table.index_select(0, order)
        grid = profile.table.shape[-1]
    else:
        table, grid = torch.zeros(1, device=means.device, dtype=torch.float32), 2
    img, alpha = _TritonPlanar.apply(
        M.reshape(-1, 9), opacities.reshape(-1).index_select(0, order), colors.index_select(0, order), table,
        background.reshape(-1).to(colors.dtype), profile.kind, grid, int(width), int(height))
    return RasterOutput(img, alpha)
