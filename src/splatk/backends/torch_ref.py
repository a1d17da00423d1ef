"""Pure-PyTorch reference rasteriser: the specification every other backend is tested against.

Runs on any device and differentiates through autograd. It enumerates (primitive, pixel) pairs
band by band (rows of 16-pixel tiles, which bounds memory), keeps the pairs inside the support
with alpha >= 1/255, sorts them by (pixel, depth) and composites with a segmented log-cumsum
of (1 - alpha) in float64. Slow but obviously correct.
"""
from __future__ import annotations

import torch

from .profiles import evaluate_profile
from .types import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE_SIZE, Profile, RasterOutput


def support_bboxes(means2d: torch.Tensor, conics: torch.Tensor, width: int, height: int):
    """Pixel bounding boxes [x0, x1) x [y0, y1) of each support ellipse r2 < 1, clipped.

    The ellipse d^T Q d = 1 has half-extents sqrt((Q^-1)_xx) and sqrt((Q^-1)_yy).
    """
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    det = (a * c - b * b).clamp_min(1e-30)
    hx = torch.sqrt((c / det).clamp_min(0))
    hy = torch.sqrt((a / det).clamp_min(0))
    # pixel i is inside when its centre i + 0.5 lies in [mx - hx, mx + hx]
    x0 = torch.ceil(means2d[:, 0] - hx - 0.5).clamp(0, width).long()
    x1 = (torch.floor(means2d[:, 0] + hx - 0.5) + 1).clamp(0, width).long()
    y0 = torch.ceil(means2d[:, 1] - hy - 0.5).clamp(0, height).long()
    y1 = (torch.floor(means2d[:, 1] + hy - 0.5) + 1).clamp(0, height).long()
    return x0, x1, y0, y1


def _pairs_in_band(x0, x1, y0, y1, band_y0: int, band_y1: int):
    """All (primitive, pixel x, pixel y) with the pixel inside the primitive's bbox and band."""
    by0 = y0.clamp(min=band_y0)
    by1 = y1.clamp(max=band_y1)
    w = (x1 - x0).clamp_min(0)
    h = (by1 - by0).clamp_min(0)
    counts = w * h
    prims = torch.nonzero(counts > 0).flatten()
    if prims.numel() == 0:
        empty = torch.zeros(0, dtype=torch.long, device=x0.device)
        return empty, empty, empty
    counts = counts[prims]
    g = torch.repeat_interleave(prims, counts)
    starts = torch.cumsum(counts, 0) - counts
    local = torch.arange(g.numel(), device=g.device) - torch.repeat_interleave(starts, counts)
    wg = w[g]
    px = x0[g] + local % wg
    py = by0[g] + local // wg
    return g, px, py


def rasterize_torch(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
    profile: Profile,
    width: int,
    height: int,
    background: torch.Tensor,
) -> RasterOutput:
    device = means2d.device
    n, channels = colors.shape
    num_pixels = width * height
    out_color = torch.zeros(num_pixels, channels, device=device, dtype=colors.dtype)
    log_t_final = torch.zeros(num_pixels, device=device, dtype=torch.float64)
    if n == 0:
        T = torch.ones(num_pixels, 1, device=device, dtype=colors.dtype)
        img = out_color + T * background[None]
        return RasterOutput(img.view(height, width, channels), (1 - T).view(height, width, 1))

    # Depth rank with a stable tie-break by index, shared by every backend.
    order = torch.sort(depths.detach(), stable=True).indices
    rank = torch.empty_like(order)
    rank[order] = torch.arange(n, device=device)

    with torch.no_grad():
        x0, x1, y0, y1 = support_bboxes(means2d.detach(), conics.detach(), width, height)

    color_parts = []
    for band_y0 in range(0, height, TILE_SIZE):
        band_y1 = min(height, band_y0 + TILE_SIZE)
        g, px, py = _pairs_in_band(x0, x1, y0, y1, band_y0, band_y1)
        if g.numel() == 0:
            continue
        dx = px.to(means2d.dtype) + 0.5 - means2d[g, 0]
        dy = py.to(means2d.dtype) + 0.5 - means2d[g, 1]
        con = conics[g]
        r2 = con[:, 0] * dx * dx + 2.0 * con[:, 1] * dx * dy + con[:, 2] * dy * dy
        with torch.no_grad():
            inside = (r2 < 1.0) & (r2 >= 0.0)
        g, px, py, r2 = g[inside], px[inside], py[inside], r2[inside]
        params = None if profile.params is None else profile.params[g]
        prof = evaluate_profile(profile.kind, r2, params)
        alpha = torch.clamp(opacities[g] * prof, max=ALPHA_MAX)
        with torch.no_grad():
            keep = alpha >= ALPHA_MIN
        g, px, py, alpha = g[keep], px[keep], py[keep], alpha[keep]
        if g.numel() == 0:
            continue
        pix = py * width + px
        key = pix * n + rank[g]
        srt = torch.argsort(key)
        g, pix, alpha = g[srt], pix[srt], alpha[srt]
        # Segmented exclusive cumsum of log(1 - alpha) per pixel, in float64.
        log1m = torch.log1p(-alpha.double())
        cs = torch.cumsum(log1m, 0)
        excl = cs - log1m
        new_seg = torch.ones_like(pix, dtype=torch.bool)
        new_seg[1:] = pix[1:] != pix[:-1]
        seg_id = torch.cumsum(new_seg.long(), 0) - 1
        seg_base = excl[new_seg]
        log_t_before = excl - seg_base[seg_id]
        log_t_after = log_t_before + log1m
        with torch.no_grad():
            # T is non-increasing, so the blended pairs form a prefix of each pixel's list.
            blended = log_t_after >= torch.log(torch.tensor(T_MIN, dtype=torch.float64))
        weight = (alpha.double() * torch.exp(log_t_before)).to(colors.dtype)
        weight = weight * blended.to(colors.dtype)
        contrib = weight[:, None] * colors[g]
        color_parts.append((pix, contrib))
        log_t_final = log_t_final.index_add(
            0, pix, torch.where(blended, log1m, torch.zeros_like(log1m))
        )
    for pix, contrib in color_parts:
        out_color = out_color.index_add(0, pix, contrib)
    T = torch.exp(log_t_final).to(colors.dtype)[:, None]
    img = out_color + T * background[None]
    return RasterOutput(img.view(height, width, channels), (1.0 - T).view(height, width, 1))
