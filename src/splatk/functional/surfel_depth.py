"""Per-surfel geometry channels whose alpha-blend gives per-pixel normals and inverse-depth moments.

A planar primitive lies in the camera-space plane ``n . X = d`` (``n`` its unit normal, turned to
face the camera, ``d = n . p_cam < 0``). A pixel's ray ``X = z r`` with ``r = K^-1 (x, y, 1)``
meets that plane at depth ``z = d / (n . r)``, so with ``q = n / d``::

    1 / z = q . r                     (exact for every pixel, not only at the centre)

Blending ``q`` and the six unique entries of ``q q^T`` as extra colour channels (background 0)
with the blending weights ``b_i`` of a pixel (``A = sum_i b_i`` is its alpha) gives::

    E[1/z]   = sum_i b_i q_i . r          = q_bar . r
    E[1/z^2] = sum_i b_i (q_i . r)^2      = r^T (q q^T)_bar r

so any rasteriser that composites C channels yields both moments, and the blended normal
``E[n] = sum_i b_i n_i`` from three more channels: the inputs of 2DGS's normal consistency and
depth distortion (:mod:`splatk.train.planar_regularisers`).
"""
from __future__ import annotations

import torch

from .projection import quats_to_rotmats

#: channels per surfel: normal (3), q (3), the unique entries of q q^T (6)
GEOMETRY_CHANNELS = 12
#: (row, column) of the unique entries of q q^T, in channel order after the normal and q
QQ_ENTRIES = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
#: |n . p_cam| / |p_cam| floor: the cosine below which a disk counts as edge-on
EDGE_ON = 1e-6


def surfel_geometry_channels(means: torch.Tensor, quats: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    """[N, 12] per-surfel channels to composite: camera-space normal facing the camera (3),
    ``q = n / (n . p_cam)`` (3), and ``q q^T`` at :data:`QQ_ENTRIES` (6).

    Args:
        means: [N, 3] disk centres (world); quats: [N, 4] (w, x, y, z), column 2 of the
            rotation is the normal; viewmat: [4, 4] world->camera.
    """
    rw, tw = viewmat[:3, :3], viewmat[:3, 3]
    p_cam = means @ rw.T + tw
    normals = quats_to_rotmats(quats)[:, :, 2] @ rw.T
    d = (normals * p_cam).sum(-1, keepdim=True)
    # the side facing the camera: a normal pointing away from it (n . p_cam > 0) is flipped,
    # so d = -|d|; an edge-on disk (plane through the camera) draws no pixel, and the floor
    # keeps its q finite
    normals = normals * torch.where(d > 0, -1.0, 1.0).to(d.dtype)
    dist = d.abs().clamp_min(EDGE_ON * p_cam.norm(dim=-1, keepdim=True))
    q = -normals / dist
    qq = torch.stack([q[:, i] * q[:, j] for i, j in QQ_ENTRIES], -1)
    return torch.cat([normals, q, qq], -1)


def pixel_centres(width: int, height: int, dtype: torch.dtype, device) -> torch.Tensor:
    """[H, W, 2] pixel-centre coordinates (x, y), integer + 0.5, the rasterisers' convention."""
    ys, xs = torch.meshgrid(torch.arange(height, dtype=dtype, device=device) + 0.5,
                            torch.arange(width, dtype=dtype, device=device) + 0.5, indexing="ij")
    return torch.stack([xs, ys], -1)


def pixel_rays(K: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[H, W, 3] rays ``K^-1 (x, y, 1)`` through the pixel centres, z = 1."""
    pix = pixel_centres(width, height, K.dtype, K.device)
    pix = torch.cat([pix, torch.ones_like(pix[..., :1])], -1)
    return pix @ torch.linalg.inv(K).T


def inverse_depth_moments(geometry: torch.Tensor, rays: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel ``(E[1/z], E[1/z^2])`` ([H, W] each, weighted sums: not divided by alpha) from
    the blended channels of :func:`surfel_geometry_channels` ([H, W, 12]) and
    :func:`pixel_rays` ([H, W, 3])."""
    q_bar, qq_bar = geometry[..., 3:6], geometry[..., 6:12]
    first = (q_bar * rays).sum(-1)
    x, y, z = rays[..., 0], rays[..., 1], rays[..., 2]
    # r^T Q r with Q symmetric: the diagonal once, the off-diagonal entries twice
    products = torch.stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z], -1)
    second = (qq_bar * products).sum(-1)
    return first, second
