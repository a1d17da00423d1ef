"""Pictures of fitted image splats: each splat's outline, and the kernels of the largest ones."""
from __future__ import annotations

import math

import numpy as np
import torch

from .model import Splats2D


def primitives_picture(model: Splats2D, scale: int = 2) -> "object":
    """PIL image: each splat's 1-sigma ellipse outlined in its (clamped) colour on grey."""
    from PIL import Image, ImageDraw

    with torch.no_grad():
        means = model.means_px() * scale
        l11, l21, l22 = model.chol_factors()
        cols = (model.colors.clamp(0, 1) * 255).round().to(torch.uint8).tolist()
        t = torch.linspace(0, 2 * math.pi, 25)
        circ = torch.stack([torch.cos(t), torch.sin(t)], -1)  # [T, 2]
        ex = l11[:, None] * circ[None, :, 0]
        ey = l21[:, None] * circ[None, :, 0] + l22[:, None] * circ[None, :, 1]  # L @ circle
        pts = torch.stack([ex, ey], -1) * scale + means[:, None, :]
    im = Image.new("RGB", (model.width * scale, model.height * scale), (40, 40, 40))
    draw = ImageDraw.Draw(im)
    for p, c in zip(pts.tolist(), cols):
        draw.line([tuple(q) for q in p], fill=tuple(c), width=1)
    return im


def kernels_picture(model: Splats2D, count: int = 16, res: int = 48) -> "object":
    """PIL image: k(u, v) of the ``count`` largest splats on a 4-wide mosaic."""
    from PIL import Image

    with torch.no_grad():
        l11, l21, l22 = model.chol_factors()
        order = torch.argsort(l11 * l22, descending=True)[:count]
        g = torch.linspace(-1, 1, res)
        vv, uu = torch.meshgrid(g, g, indexing="ij")
        uv = torch.stack([uu, vv], -1).reshape(-1, 2)
        table = model.kernel2d.table(model)
        tiles = []
        for i in order.tolist():
            idx = torch.full((uv.shape[0],), i, dtype=torch.long)
            k = model.kernel_values(uv, idx, table).reshape(res, res)
            k = k / k.abs().max().clamp_min(1e-8)
            rgb = torch.stack([k.clamp(min=0), torch.zeros_like(k), (-k).clamp(min=0)], -1)
            tiles.append(torch.nn.functional.pad(rgb.permute(2, 0, 1), (1, 1, 1, 1), value=0.3))
    cols = 4
    while len(tiles) % cols:
        tiles.append(torch.full_like(tiles[0], 0.3))
    rows = [torch.cat(tiles[r:r + cols], 2) for r in range(0, len(tiles), cols)]
    arr = (torch.cat(rows, 1).permute(1, 2, 0).numpy() * 255).astype(np.uint8)
    return Image.fromarray(arr).resize((arr.shape[1] * 2, arr.shape[0] * 2), Image.NEAREST)
