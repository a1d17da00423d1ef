"""Planar primitives: the 2DGS ray-splat (u, v) against a direct ray-plane solve, in float64."""
from __future__ import annotations

import torch

from splatk.backends.planar_torch import ray_splat_uv, splat_homographies
from splatk.functional.projection import quats_to_rotmats


def test_uv_matches_ray_plane_float64():
    gen = torch.Generator().manual_seed(0)
    dt = torch.float64
    n = 64
    means = torch.randn(n, 3, generator=gen, dtype=dt) + torch.tensor([0, 0, 6.0], dtype=dt)
    quats = torch.randn(n, 4, generator=gen, dtype=dt)
    quats = quats / quats.norm(dim=-1, keepdim=True)
    scales = torch.rand(n, 2, generator=gen, dtype=dt) * 0.5 + 0.05
    ang = torch.tensor(0.3, dtype=dt)
    rw = torch.tensor([[1, 0, 0], [0, torch.cos(ang), -torch.sin(ang)], [0, torch.sin(ang), torch.cos(ang)]],
                      dtype=dt)
    viewmat = torch.eye(4, dtype=dt)
    viewmat[:3, :3] = rw
    viewmat[:3, 3] = torch.tensor([0.2, -0.1, 0.5], dtype=dt)
    K = torch.tensor([[300.0, 0, 160], [0, 310.0, 120], [0, 0, 1]], dtype=dt)
    pixels = torch.rand(n, 2, generator=gen, dtype=dt) * torch.tensor([320.0, 240.0], dtype=dt)

    uv = ray_splat_uv(splat_homographies(means, quats, scales, viewmat, K), pixels)

    # reference: o + lam d = p + u s_u t_u + v s_v t_v, solved in world space
    origin = -rw.T @ viewmat[:3, 3]
    d_cam = torch.linalg.solve(K, torch.cat([pixels, torch.ones(n, 1, dtype=dt)], 1).T).T
    dirs = d_cam @ rw  # R^T d
    rot = quats_to_rotmats(quats)
    A = torch.stack([rot[:, :, 0] * scales[:, :1], rot[:, :, 1] * scales[:, 1:], -dirs], -1)
    sol = torch.linalg.solve(A, (origin - means)[..., None])[..., 0]
    torch.testing.assert_close(uv, sol[:, :2], atol=1e-9, rtol=1e-9)
