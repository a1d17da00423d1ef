"""Planar (2DGS-style surfel) primitives: ray-splat intersection in pure torch (the specification).

A planar primitive is an oriented disk: centre ``p`` (means [N, 3]), rotation ``R = [t_u t_v n]``
(quats [N, 4], wxyz) and two scales ``s_u, s_v`` (scales [N, 2]); its local point ``(u, v)``
sits at ``p + u s_u t_u + v s_v t_v`` (2DGS, Huang et al. 2024, Eq. 4-5).

For a camera (``viewmat`` world->camera [4, 4], intrinsics ``K`` [3, 3]) the homogeneous map from
(u, v, 1) to homogeneous pixels is the 3x3 matrix ``M = K [R_w s_u t_u | R_w s_v t_v | R_w p + t_w]``
(rows M0, M1, M2). A pixel (x, y) lies on the planes ``h_u = -M0 + x M2`` and ``h_v = -M1 + y M2``
in (u, v, 1) space, so the intersection is (2DGS Eq. 9-10; peers.md Sec. 5)::

    (u', v', w') = h_u x h_v,      (u, v) = (u' / w', v' / w')

This file holds that intersection (used by a planar rasteriser; the learned planar kernel then
evaluates Phi_dec_planar(u, v, z) at it). The rasteriser itself is not written yet.
"""
from __future__ import annotations

import torch

from ..functional.projection import quats_to_rotmats


def splat_homographies(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                       viewmat: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """[N, 3, 3] matrices M mapping (u, v, 1) to homogeneous pixel coordinates.

    Args:
        means: [N, 3] disk centres (world).
        quats: [N, 4] rotations (w, x, y, z); columns 0 and 1 of the rotation are t_u, t_v.
        scales: [N, 2] s_u, s_v.
        viewmat: [4, 4] world->camera.
        K: [3, 3] intrinsics.
    """
    rot = quats_to_rotmats(quats)  # [N, 3, 3]
    rw, tw = viewmat[:3, :3], viewmat[:3, 3]
    cols = torch.stack([
        rot[:, :, 0] * scales[:, 0:1],
        rot[:, :, 1] * scales[:, 1:2],
        means,
    ], -1)  # [N, 3, 3] world: columns s_u t_u, s_v t_v, p
    cam = rw @ cols
    cam = torch.cat([cam[:, :, :2], cam[:, :, 2:] + tw[:, None]], -1)
    return K @ cam


def ray_splat_uv(M: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:
    """Local (u, v) where each pixel's ray meets its splat's plane (2DGS Eq. 10).

    Args:
        M: [P, 3, 3] homography of the splat of each (splat, pixel) pair.
        pixels: [P, 2] pixel coordinates (x, y) (pixel centres are integer + 0.5).
    Returns:
        [P, 2] (u, v) in units of the scales (|(u, v)| = 3 is the 3-sigma edge of a Gaussian surfel).
    """
    x, y = pixels[:, 0:1], pixels[:, 1:2]
    h_u = -M[:, 0] + x * M[:, 2]
    h_v = -M[:, 1] + y * M[:, 2]
    c = torch.linalg.cross(h_u, h_v)
    return c[:, :2] / c[:, 2:3]
