"""Stateless helpers of planar (2DGS-style surfel) primitives, shared by the planar kernels, the
image splats and the planar rasterisers: the Gaussian surfel profile, per-primitive bilinear
tables, and which disks lie wholly in front of a camera."""
from __future__ import annotations

import torch

from .projection import quats_to_rotmats

#: splats whose centre or 3-sigma-square corners are nearer than this (camera z) are not drawn
NEAR = 1e-2
#: a planar splat's (u, v) support in sigmas: (u, v) normalised by it lie in the unit disk
SURFEL_SUPPORT_SIGMAS = 3.0


def gaussian_surfel(uv: torch.Tensor) -> torch.Tensor:
    """Gaussian surfel exp(-(u^2 + v^2) S^2 / 2) at normalised (u, v) (S = 3), 0 outside the disk.

    Args:
        uv: [..., 2] normalised (u, v).
    Returns:
        [...] profile values.
    """
    r2 = (uv * uv).sum(-1)
    return torch.exp(-0.5 * SURFEL_SUPPORT_SIGMAS**2 * r2) * (r2 <= 1.0)


def bilinear(table: torch.Tensor, idx: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Sample per-primitive tables at (u, v).

    Args:
        table: [N, G, G] values at nodes ``linspace(-1, 1, G)``, indexed [v, u].
        idx: [P] primitive of each sample.
        uv: [P, 2] in [-1, 1] (clamped).
    Returns:
        [P] bilinearly interpolated values (exact at the nodes).
    """
    g = table.shape[-1]
    t = ((uv.clamp(-1.0, 1.0) + 1.0) * 0.5 * (g - 1))
    i0 = t.detach().floor().clamp(0, g - 2)
    f = t - i0
    i0 = i0.long()
    flat = table.reshape(-1)
    base = idx * (g * g) + i0[:, 1] * g + i0[:, 0]
    fu, fv = f[:, 0], f[:, 1]
    t00, t01 = flat[base], flat[base + 1]
    t10, t11 = flat[base + g], flat[base + g + 1]
    return (t00 * (1 - fu) + t01 * fu) * (1 - fv) + (t10 * (1 - fu) + t11 * fu) * fv


def planar_in_front(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                    viewmat: torch.Tensor) -> torch.Tensor:
    """[N] bool: the splat's centre and the four corners of its 3-sigma square lie at camera
    depth > ``NEAR``. Then the whole disk is in front of the camera and its image is an ellipse.

    The corners' depths are ``z + 3 (+-a s_u +- b s_v)`` with ``a``, ``b`` the camera-z
    components of the disk's axes, so the nearest is ``z - 3 (|a| s_u + |b| s_v)``. Disks that
    cross the camera plane are rare and dropped whole, in every backend.

    Args:
        means: [N, 3]; quats: [N, 4] (w, x, y, z); scales: [N, 2]; viewmat: [4, 4] world->camera.
    """
    with torch.no_grad():
        rz, tz = viewmat[2, :3], viewmat[2, 3]
        depth = means @ rz + tz
        axes_z = quats_to_rotmats(quats)[:, :, :2].mT @ rz  # [N, 2]: camera z of t_u, t_v
        nearest = depth - 3.0 * (axes_z.abs() * scales).sum(1)
        return (depth > NEAR) & (nearest > NEAR)
