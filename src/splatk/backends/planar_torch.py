"""Planar (2DGS-style surfel) primitives: ray-splat intersection in pure torch (the specification).

A planar primitive is an oriented disk: centre ``p`` (means [N, 3]), rotation ``R = [t_u t_v n]``
(quats [N, 4], wxyz) and two scales ``s_u, s_v`` (scales [N, 2]); its local point ``(u, v)``
sits at ``p + u s_u t_u + v s_v t_v`` (2DGS, Huang et al. 2024, Eq. 4-5).

For a camera (``viewmat`` world->camera [4, 4], intrinsics ``K`` [3, 3]) the homogeneous map from
(u, v, 1) to homogeneous pixels is the 3x3 matrix ``M = K [R_w s_u t_u | R_w s_v t_v | R_w p + t_w]``
(rows M0, M1, M2). A pixel (x, y) lies on the planes ``h_u = -M0 + x M2`` and ``h_v = -M1 + y M2``
in (u, v, 1) space, so the intersection is (2DGS Eq. 9-10; peers.md Sec. 5)::

    (u', v', w') = h_u x h_v,      (u, v) = (u' / w', v' / w')

:func:`rasterize_planar` is the dense pure-torch reference rasteriser built on it: every
(pixel, splat) pair, (u, v) normalised by the 3-sigma extent (so the support is the unit disk),
``alpha = min(0.999, o * k(u, v))``, pairs with ``alpha < 1/255`` skipped, front-to-back
compositing by camera depth of the centres (stable), a pixel ending before the splat whose
``T * (1 - alpha)`` would fall below ``1e-4`` (T in float64 log space), as the volumetric
contract in :mod:`splatk.backends`. Which splats are drawn at all is
:func:`~splatk.functional.planar.planar_in_front`: centre and the four corners of the 3-sigma
square at camera depth > ``NEAR`` (a disk crossing the camera plane is dropped whole, in every
backend). It omits 2DGS's screen-space low-pass fallback (peers.md Sec. 5) and is meant for
small images (tests, checks); the native tiled version is :mod:`splatk.backends.planar_cpu`.
Both are the ``rasterize_planar`` op of their backend object.
"""
from __future__ import annotations

import math
from typing import Callable

import torch

from ..functional.planar import bilinear, gaussian_surfel, planar_in_front
from ..functional.projection import quats_to_rotmats
from ..functional.surfel_depth import pixel_centres
from .types import ALPHA_MAX, ALPHA_MIN, PLANAR_PROFILE_KINDS, T_MIN, PlanarProfile, RasterOutput

#: the dense reference holds ~20 float tensors of this many pairs: ~2 GB in float32 at the cap
MAX_DENSE_PAIRS = 25_000_000


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
    # (A @ B^T)^T with a 2D right operand: torch folds the batch into one mm (a broadcast
    # rw @ cols runs as a much slower bmm of 3x3 blocks)
    cam = (cols.mT @ rw.T).mT
    cam = torch.cat([cam[:, :, :2], cam[:, :, 2:] + tw[:, None]], -1)
    return (cam.mT @ K.T).mT


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


def profile_function(profile: PlanarProfile) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """``kernel(uv [P, 2], idx [P]) -> [P]`` of a :class:`PlanarProfile` (0 outside the unit disk)."""
    if profile.kind == "gaussian_surfel":
        return lambda uv, idx: gaussian_surfel(uv)
    if profile.kind == "grid":
        if profile.table is None:
            raise ValueError("planar profile 'grid' needs a table [N, G, G]")
        return lambda uv, idx: bilinear(profile.table, idx, uv) * ((uv * uv).sum(-1) <= 1.0)
    raise ValueError(f"unknown planar profile {profile.kind!r}; choose from {', '.join(PLANAR_PROFILE_KINDS)}")


def planar_visible(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                   viewmat: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The splats every backend draws (:func:`planar_in_front`), front to back by the camera
    depth of their centres (stable: ties by index), and their homographies.

    Returns:
        order [m] primitive indices, M [m, 3, 3].
    """
    with torch.no_grad():
        idx = torch.nonzero(planar_in_front(means, quats, scales, viewmat)).flatten()
        depth = means.index_select(0, idx) @ viewmat[2, :3] + viewmat[2, 3]
        order = idx[torch.argsort(depth, stable=True)]
    M = splat_homographies(means[order], quats[order], scales[order], viewmat, K)
    return order, M


def rasterize_planar(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                     opacities: torch.Tensor, colors: torch.Tensor, viewmat: torch.Tensor,
                     K: torch.Tensor, width: int, height: int,
                     kernel: "Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | PlanarProfile",
                     background: torch.Tensor | None = None) -> RasterOutput:
    """Dense reference rasteriser for planar primitives.

    Args:
        means, quats, scales: [N, 3], [N, 4], [N, 2] disks (see :func:`splat_homographies`).
        opacities: [N]; colors: [N, C].
        viewmat, K: [4, 4] world->camera, [3, 3] intrinsics.
        width, height: image size.
        kernel: a :class:`PlanarProfile`, or ``kernel(uv [P, 2], idx [P]) -> [P]`` opacity
            profile at normalised (u, v) (unit disk support), e.g.
            ``lambda uv, idx: gaussian_surfel(uv)`` or a learned planar kernel's table lookup.
        background: [C] or None (zeros).
    Returns:
        RasterOutput(colors [H, W, C], alphas [H, W, 1]).
    """
    if isinstance(kernel, PlanarProfile):
        kernel = profile_function(kernel)
    dtype = colors.dtype
    order, M = planar_visible(means, quats, scales, viewmat, K)
    dev = means.device
    pix = pixel_centres(width, height, means.dtype, dev).reshape(-1, 2)  # [HW, 2]
    hw, m = pix.shape[0], order.numel()
    if hw * m > MAX_DENSE_PAIRS:
        raise ValueError(f"the dense planar reference would build {hw * m:,} (pixel, splat) pairs "
                         f"(at most {MAX_DENSE_PAIRS:,}); render planar scenes of this size with "
                         "backend 'cpu' (the native rasteriser)")
    c = colors.shape[-1]
    if m == 0:
        out = torch.zeros(hw, c, dtype=dtype, device=dev)
        t_final = torch.ones(hw, 1, dtype=dtype, device=dev)
    else:
        pair_pix = pix[:, None, :].expand(hw, m, 2).reshape(-1, 2)
        pair_idx = torch.arange(m, device=dev).repeat(hw)
        uv = ray_splat_uv(M[pair_idx], pair_pix) / 3.0  # 3-sigma extent -> unit disk
        k = kernel(uv, order[pair_idx]).reshape(hw, m)
        alpha = (opacities[order][None, :] * k).clamp(max=ALPHA_MAX)
        alpha = alpha * (alpha >= ALPHA_MIN)
        # Transmittance in float64 log space; a pixel ends before the splat that would take T
        # below T_MIN (non-increasing, so the blended splats are a prefix of each pixel's list).
        log1m = torch.log1p(-alpha.double())
        log_before = torch.cumsum(log1m, 1) - log1m
        with torch.no_grad():
            blended = (log_before + log1m) >= math.log(T_MIN)
        w = (alpha.double() * torch.exp(log_before) * blended).to(dtype)
        out = w @ colors[order]
        t_final = torch.exp((log1m * blended).sum(1, keepdim=True)).to(dtype)
    if background is not None:
        out = out + t_final * background
    return RasterOutput(out.reshape(height, width, c), (1.0 - t_final).reshape(height, width, 1))
