"""Tile-based rasteriser in Triton: forward and backward kernels (one program per 16x16 tile).

Same contract as :func:`splatk.backends.torch_ref.rasterize_torch` (see :mod:`splatk.backends`).
Binning runs as torch ops on the device (:mod:`.triton_binning`); each program walks its
tile's primitives in depth order, one primitive at a time over the tile's 256 pixels.

The backward walks each pixel's list back to front from its last blended primitive, as 3DGS
does: the transmittance before a primitive is recovered as ``T / (1 - alpha)`` and the colour
of everything behind it is summed as it goes, so ``dL/dalpha`` needs no subtraction of two
nearly equal sums. Per-primitive gradients are summed over the tile's pixels in the program
and added to global memory with one atomic add per (primitive, tile, quantity): on a GPU the
order of those adds varies, so gradients are not bit-identical from run to run.

Profiles are compiled in (``KIND``: 0 gaussian, 1 beta, 2 student_t, 3 table with ``K``
samples); colour channels are a padded vector of ``CP`` (the next power of two >= C) lanes.
"""
from __future__ import annotations

import triton
import triton.language as tl

from .types import ALPHA_MAX, ALPHA_MIN, GAUSSIAN_SUPPORT_SIGMAS, STUDENT_T_SUPPORT_SIGMAS, T_MIN, TILE_SIZE

PROFILE_CODES = {"gaussian": 0, "beta": 1, "student_t": 2, "table": 3}

_GS2 = GAUSSIAN_SUPPORT_SIGMAS**2
_TS2 = STUDENT_T_SUPPORT_SIGMAS**2


@triton.jit
def pixel_block(tile, tiles_x, width, height, TILE: tl.constexpr):
    """Pixel coordinates of a tile's TILE*TILE pixels (row-major) and which lie in the image."""
    lin = tl.arange(0, TILE * TILE)
    px = (tile % tiles_x) * TILE + lin % TILE
    py = (tile // tiles_x) * TILE + lin // TILE
    return px, py, (px < width) & (py < height)


@triton.jit
def _r2(g, px, py, means_ptr, conics_ptr):
    mx = tl.load(means_ptr + 2 * g)
    my = tl.load(means_ptr + 2 * g + 1)
    ca = tl.load(conics_ptr + 3 * g)
    cb = tl.load(conics_ptr + 3 * g + 1)
    cc = tl.load(conics_ptr + 3 * g + 2)
    dx = px.to(tl.float32) + 0.5 - mx
    dy = py.to(tl.float32) + 0.5 - my
    r2 = ca * dx * dx + 2.0 * cb * dx * dy + cc * dy * dy
    return dx, dy, ca, cb, cc, r2


@triton.jit
def _profile(r2, g, params_ptr, inside, KIND: tl.constexpr, K: tl.constexpr, GS2: tl.constexpr,
             TS2: tl.constexpr):
    """Profile value at r2 (valid where ``inside``: 0 <= r2 < 1)."""
    if KIND == 0:
        prof = tl.exp(-0.5 * GS2 * r2)
    elif KIND == 1:
        beta = tl.load(params_ptr + g)
        prof = tl.exp(beta * tl.log(tl.where(inside, 1.0 - r2, 1.0)))
    elif KIND == 2:
        nu = tl.load(params_ptr + g)
        prof = tl.exp(-0.5 * (nu + 2.0) * tl.log(1.0 + TS2 * r2 / nu))
    else:
        r = tl.sqrt_rn(tl.maximum(r2, 1e-20))
        t = r * (K - 1)
        idx = tl.minimum(tl.maximum(t.to(tl.int32), 0), K - 2)
        lam = t - idx.to(tl.float32)
        d0 = tl.load(params_ptr + g * K + idx, mask=inside, other=0.0)
        d1 = tl.load(params_ptr + g * K + idx + 1, mask=inside, other=0.0)
        prof = (1.0 - lam) * d0 + lam * d1
    # outside the support the formulas may overflow (a degenerate conic's r2 < 0): 0 there, so
    # that a masked pixel's 0 upstream gradient times the profile stays 0, not NaN
    return tl.where(inside, prof, 0.0)


@triton.jit
def composite_forward_step(value, inside, g, count, T, acc, alive, n_contrib, opac_ptr, colors_ptr, ch, ch_ok, C,
                           A_MAX: tl.constexpr, A_MIN: tl.constexpr, T_STOP: tl.constexpr):
    """One primitive ``g`` of the front-to-back walk, drawn with kernel value ``value`` [P] where
    ``inside``: blends its colour into ``acc`` and returns the transmittance, the accumulator,
    the pixels still alive (3DGS's early termination) and each pixel's contributor count
    (``count``: g's place in the tile's list, from 1). Shared by the splat and the planar
    rasteriser."""
    alpha = tl.minimum(A_MAX, tl.load(opac_ptr + g) * value)
    valid = alive & inside & (alpha >= A_MIN)
    t_next = T * (1.0 - alpha)
    stop = valid & (t_next < T_STOP)
    blend = valid & (t_next >= T_STOP)
    w = tl.where(blend, alpha * T, 0.0)
    col = tl.load(colors_ptr + g * C + ch, mask=ch_ok, other=0.0)
    acc += w[:, None] * col[None, :]
    T = tl.where(blend, t_next, T)
    n_contrib = tl.where(blend, count, n_contrib)
    alive = alive & (stop == 0)
    return T, acc, alive, n_contrib


@triton.jit
def rasterize_fwd_kernel(
    means_ptr, conics_ptr, opac_ptr, colors_ptr, params_ptr, bg_ptr,
    tile_offsets_ptr, flat_ids_ptr,
    out_img_ptr, out_tfinal_ptr, out_ncontrib_ptr,
    width, height, tiles_x, C,
    KIND: tl.constexpr, K: tl.constexpr, CP: tl.constexpr, TILE: tl.constexpr,
    GS2: tl.constexpr, TS2: tl.constexpr, A_MAX: tl.constexpr, A_MIN: tl.constexpr,
    T_STOP: tl.constexpr,
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
    # the tile stops when every pixel has reached T < T_STOP (3DGS's early termination)
    while (i < end) & (any_alive > 0):
        g = tl.load(flat_ids_ptr + i)
        dx, dy, ca, cb, cc, r2 = _r2(g, px, py, means_ptr, conics_ptr)
        inside = (r2 < 1.0) & (r2 >= 0.0)
        prof = _profile(r2, g, params_ptr, inside, KIND, K, GS2, TS2)
        T, acc, alive, n_contrib = composite_forward_step(
            prof, inside, g, i - start + 1, T, acc, alive, n_contrib, opac_ptr, colors_ptr, ch, ch_ok, C,
            A_MAX, A_MIN, T_STOP)
        any_alive = tl.max(alive.to(tl.int32), axis=0)
        i += 1

    bg = tl.load(bg_ptr + ch, mask=ch_ok, other=0.0)
    img = acc + T[:, None] * bg[None, :]
    pix = py * width + px
    tl.store(out_img_ptr + pix[:, None] * C + ch[None, :], img, mask=in_img[:, None] & ch_ok[None, :])
    tl.store(out_tfinal_ptr + pix, T, mask=in_img)
    tl.store(out_ncontrib_ptr + pix, n_contrib, mask=in_img)


@triton.jit
def composite_backward_start(pix, in_img, ch, ch_ok, C, tfinal_ptr, ncontrib_ptr, v_img_ptr, v_alpha_ptr, bg_ptr):
    """What the back-to-front walk starts from at each pixel of a tile: the final transmittance
    (twice: the running one and the final one), how many primitives it blended, the upstream
    gradients of the image and the alpha, and the colour behind the last one (the background)."""
    T = tl.load(tfinal_ptr + pix, mask=in_img, other=1.0)
    n_contrib = tl.load(ncontrib_ptr + pix, mask=in_img, other=0)
    v_img = tl.load(v_img_ptr + pix[:, None] * C + ch[None, :], mask=in_img[:, None] & ch_ok[None, :],
                    other=0.0)
    v_alpha = tl.load(v_alpha_ptr + pix, mask=in_img, other=0.0)
    bg = tl.load(bg_ptr + ch, mask=ch_ok, other=0.0)
    return T, T, n_contrib, v_img, v_alpha, T[:, None] * bg[None, :]


@triton.jit
def composite_backward_step(value, live, g, T, behind, t_final, v_img, v_alpha, colors_ptr, g_colors_ptr,
                             g_opac_ptr, opac_ptr, ch, ch_ok, C, A_MAX: tl.constexpr, A_MIN: tl.constexpr):
    """One primitive ``g`` of the back-to-front walk (3DGS's backward), drawn with kernel value
    ``value`` [P] where ``live``: adds its colour and opacity gradients and returns the
    transmittance in front of it, the colour behind it, the gradient on ``value`` and where it
    was blended. Shared by the splat and the planar rasteriser."""
    opac = tl.load(opac_ptr + g)
    raw = opac * value
    alpha = tl.minimum(A_MAX, raw)
    active = live & (alpha >= A_MIN)
    one_m = 1.0 - alpha
    T = tl.where(active, T / one_m, T)
    w = tl.where(active, alpha * T, 0.0)
    col = tl.load(colors_ptr + g * C + ch, mask=ch_ok, other=0.0)
    tl.atomic_add(g_colors_ptr + g * C + ch, tl.sum(w[:, None] * v_img, axis=0), mask=ch_ok)
    v_a = tl.sum(v_img * (T[:, None] * col[None, :] - behind / one_m[:, None]), axis=1)
    v_a += v_alpha * t_final / one_m
    v_a = tl.where(active, v_a, 0.0)
    behind += w[:, None] * col[None, :]
    # the 0.999 clamp passes no gradient above it (torch.clamp's rule)
    v_raw = tl.where(raw <= A_MAX, v_a, 0.0)
    tl.atomic_add(g_opac_ptr + g, tl.sum(v_raw * value, axis=0))
    return T, behind, v_raw * opac, active


@triton.jit
def rasterize_bwd_kernel(
    means_ptr, conics_ptr, opac_ptr, colors_ptr, params_ptr, bg_ptr,
    tile_offsets_ptr, flat_ids_ptr, tfinal_ptr, ncontrib_ptr, v_img_ptr, v_alpha_ptr,
    g_means_ptr, g_conics_ptr, g_opac_ptr, g_colors_ptr, g_params_ptr,
    width, height, tiles_x, C,
    KIND: tl.constexpr, K: tl.constexpr, KP: tl.constexpr, CP: tl.constexpr, TILE: tl.constexpr,
    GS2: tl.constexpr, TS2: tl.constexpr, A_MAX: tl.constexpr, A_MIN: tl.constexpr,
):
    tile = tl.program_id(0)
    px, py, in_img = pixel_block(tile, tiles_x, width, height, TILE)
    pix = py * width + px
    ch = tl.arange(0, CP)
    ch_ok = ch < C
    start = tl.load(tile_offsets_ptr + tile)

    # behind: the colour of everything behind the current primitive, background included
    T, t_final, n_contrib, v_img, v_alpha, behind = composite_backward_start(
        pix, in_img, ch, ch_ok, C, tfinal_ptr, ncontrib_ptr, v_img_ptr, v_alpha_ptr, bg_ptr)
    last = tl.max(n_contrib, axis=0)
    for j in range(0, last):
        local = last - 1 - j
        g = tl.load(flat_ids_ptr + start + local)
        dx, dy, ca, cb, cc, r2 = _r2(g, px, py, means_ptr, conics_ptr)
        inside = (r2 < 1.0) & (r2 >= 0.0)
        prof = _profile(r2, g, params_ptr, inside, KIND, K, GS2, TS2)
        T, behind, v_prof, active = composite_backward_step(
            prof, (local < n_contrib) & inside, g, T, behind, t_final, v_img, v_alpha, colors_ptr, g_colors_ptr,
            g_opac_ptr, opac_ptr, ch, ch_ok, C, A_MAX, A_MIN)
        # d profile / d r2 and the profile parameters' gradients
        if KIND == 0:
            v_r2 = v_prof * (-0.5 * GS2) * prof
        elif KIND == 1:
            beta = tl.load(params_ptr + g)
            one_m_r2 = tl.where(inside, 1.0 - r2, 1.0)
            v_r2 = -v_prof * beta * prof / one_m_r2
            tl.atomic_add(g_params_ptr + g, tl.sum(v_prof * prof * tl.log(one_m_r2), axis=0))
        elif KIND == 2:
            nu = tl.load(params_ptr + g)
            u = TS2 * r2 / nu
            v_r2 = v_prof * prof * (-0.5 * (nu + 2.0)) * (TS2 / nu) / (1.0 + u)
            d_nu = prof * (-0.5 * tl.log(1.0 + u) + 0.5 * (nu + 2.0) * u / (nu * (1.0 + u)))
            tl.atomic_add(g_params_ptr + g, tl.sum(tl.where(active, v_prof * d_nu, 0.0), axis=0))
        else:
            r = tl.sqrt_rn(tl.maximum(r2, 1e-20))
            t = r * (K - 1)
            idx = tl.minimum(tl.maximum(t.to(tl.int32), 0), K - 2)
            lam = t - idx.to(tl.float32)
            d0 = tl.load(params_ptr + g * K + idx, mask=active, other=0.0)
            d1 = tl.load(params_ptr + g * K + idx + 1, mask=active, other=0.0)
            dr_dr2 = tl.where(r2 > 1e-20, 0.5 / r, 0.0)
            v_r2 = v_prof * (d1 - d0) * (K - 1) * dr_dr2
            # samples: (1 - lam) to idx, lam to idx + 1, summed over the tile per sample
            kk = tl.arange(0, KP)
            share = (tl.where(kk[None, :] == idx[:, None], (1.0 - lam)[:, None], 0.0)
                     + tl.where(kk[None, :] == idx[:, None] + 1, lam[:, None], 0.0))
            tl.atomic_add(g_params_ptr + g * K + kk, tl.sum(v_prof[:, None] * share, axis=0), mask=kk < K)
        v_r2 = tl.where(active, v_r2, 0.0)
        tl.atomic_add(g_means_ptr + 2 * g, tl.sum(-v_r2 * 2.0 * (ca * dx + cb * dy), axis=0))
        tl.atomic_add(g_means_ptr + 2 * g + 1, tl.sum(-v_r2 * 2.0 * (cb * dx + cc * dy), axis=0))
        tl.atomic_add(g_conics_ptr + 3 * g, tl.sum(v_r2 * dx * dx, axis=0))
        tl.atomic_add(g_conics_ptr + 3 * g + 1, tl.sum(v_r2 * 2.0 * dx * dy, axis=0))
        tl.atomic_add(g_conics_ptr + 3 * g + 2, tl.sum(v_r2 * dy * dy, axis=0))


def launch_constants(kind: str, k: int, channels: int) -> dict:
    """The compile-time arguments both kernels share for a profile and channel count.

    Fused multiply-adds are off: r2 and the profile then round exactly as the torch reference's
    separate ops do, so a pixel on the support's edge (r2 near 1, where a profile can jump from
    0.011 * o to 0) is inside or outside in both alike.
    """
    return dict(KIND=PROFILE_CODES[kind], K=k, CP=triton.next_power_of_2(max(channels, 1)), TILE=TILE_SIZE,
                GS2=_GS2, TS2=_TS2, A_MAX=ALPHA_MAX, A_MIN=ALPHA_MIN, enable_fp_fusion=False)


__all__ = ["PROFILE_CODES", "T_MIN", "launch_constants", "rasterize_bwd_kernel", "rasterize_fwd_kernel"]
