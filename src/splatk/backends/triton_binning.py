"""Binning for the Triton tile rasterisers, as torch ops on the device: which 16x16 tiles each
primitive touches, all (primitive, tile) pairs sorted by (tile, depth rank) with one sort of
64-bit keys (a radix sort on CUDA), and each tile's range of the sorted list."""
from __future__ import annotations

import torch

from .torch_ref import support_bboxes
from .types import TILE_SIZE


def bin_pairs(means2d: torch.Tensor, conics: torch.Tensor, depths: torch.Tensor, width: int,
              height: int):
    """Sort (primitive, tile) pairs by (tile, depth) and find each tile's range.

    Returns:
        flat_ids: int32 [P] primitive index per pair, tile-major and front to back in a tile.
        tile_offsets: int32 [tiles + 1]; tile t owns ``flat_ids[tile_offsets[t]:tile_offsets[t+1]]``.
        tiles_x: tiles per row.
    """
    n = means2d.shape[0]
    # depth rank with a stable tie-break by index, as every backend composites
    order = torch.sort(depths, stable=True).indices
    rank = torch.empty_like(order)
    rank[order] = torch.arange(n, device=means2d.device)
    x0, x1, y0, y1 = support_bboxes(means2d, conics, width, height)
    return bin_boxes(x0, x1, y0, y1, rank, order, width, height)


def bin_boxes(x0, x1, y0, y1, rank, order, width: int, height: int):
    """:func:`bin_pairs` for given half-open pixel boxes [x0, x1) x [y0, y1) (int64 [N] each),
    depth ranks ``rank`` and their inverse ``order`` (primitive of each rank)."""
    device, n = x0.device, x0.shape[0]
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    num_tiles = tiles_x * ((height + TILE_SIZE - 1) // TILE_SIZE)
    tx0, ty0 = x0 // TILE_SIZE, y0 // TILE_SIZE
    tx1 = (x1 + TILE_SIZE - 1) // TILE_SIZE
    ty1 = (y1 + TILE_SIZE - 1) // TILE_SIZE
    tw = (tx1 - tx0).clamp_min(0)
    counts = tw * (ty1 - ty0).clamp_min(0)
    counts = torch.where((x1 > x0) & (y1 > y0), counts, torch.zeros_like(counts))
    ends = torch.cumsum(counts, 0)
    # the one host sync of a render: the pair count sizes the buffers below
    total = int(ends[-1]) if n else 0
    if total == 0:
        return (torch.zeros(0, dtype=torch.int32, device=device),
                torch.zeros(num_tiles + 1, dtype=torch.int32, device=device), tiles_x)
    prim = torch.repeat_interleave(torch.arange(n, device=device), counts, output_size=total)
    local = torch.arange(total, device=device) - (ends - counts)[prim]
    tile = (ty0[prim] + local // tw[prim]) * tiles_x + tx0[prim] + local % tw[prim]
    keys = torch.sort(tile * n + rank[prim]).values
    flat_ids = order[keys % n].to(torch.int32)
    tile_offsets = torch.searchsorted(keys // n, torch.arange(num_tiles + 1, device=device))
    return flat_ids, tile_offsets.to(torch.int32), tiles_x
