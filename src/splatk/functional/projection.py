"""EWA projection of 3D ellipsoids to 2D conics (Zwicker et al. 2001; paper Eq. 1)."""
from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F


def quats_to_rotmats(quats: torch.Tensor) -> torch.Tensor:
    """[N, 4] (w, x, y, z), not necessarily normalised -> [N, 3, 3] rotation matrices."""
    q = F.normalize(quats, dim=-1)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).view(-1, 3, 3)


def covariances_3d(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Sigma = R S S^T R^T.  quats [N, 4], scales [N, 3] (activated) -> [N, 3, 3]."""
    R = quats_to_rotmats(quats)
    M = R * scales[:, None, :]
    return M @ M.transpose(1, 2)


class Projected(NamedTuple):
    """Per-primitive screen-space quantities for one camera (only ``visible`` ones are kept
    by callers; all tensors have the full N rows).

    Attributes:
        means2d: [N, 2] pixel coordinates.
        conics: [N, 3] (a, b, c) of the *normalised* inverse 2D covariance: r2 = 1 on the
            support ellipse at ``support_sigmas`` sigma.
        depths: [N] camera-space z.
        visible: [N] bool, in front of the near plane and support overlapping the image.
        means_cam: [N, 3] camera-space centres.
        rotmats_cam: [N, 3, 3] primitive rotation in camera space (R_cam of paper Eq. 5).
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    visible: torch.Tensor
    means_cam: torch.Tensor
    rotmats_cam: torch.Tensor


def project_ellipsoids(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    world_to_cam: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    support_sigmas: float = 3.0,
    near: float = 0.01,
    blur: float = 0.3,
) -> Projected:
    """Project ellipsoids with the EWA Jacobian and a ``blur`` px^2 low-pass (3DGS, DBS).

    Args:
        means: [N, 3] world centres.  quats: [N, 4].  scales: [N, 3] activated (positive).
        world_to_cam: [4, 4].  K: [3, 3].
        support_sigmas: the kernel's support in units of sigma; conics are divided by its
            square so that the support ellipse is r2 = 1.
    """
    Rw = world_to_cam[:3, :3]
    tw = world_to_cam[:3, 3]
    means_cam = means @ Rw.T + tw
    x, y, z = means_cam.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    zc = z.clamp_min(near)
    # Evaluate the Jacobian at most 15% of the image width outside the frustum (3DGS clamps
    # at 1.3x tan(fov/2)), so that splats far outside the view do not blow up.
    tx = (x / zc).clamp((-cx - 0.15 * width) / fx, (width - cx + 0.15 * width) / fx)
    ty = (y / zc).clamp((-cy - 0.15 * height) / fy, (height - cy + 0.15 * height) / fy)
    zero = torch.zeros_like(zc)
    J = torch.stack(
        [fx / zc, zero, -fx * tx / zc, zero, fy / zc, -fy * ty / zc], dim=-1
    ).view(-1, 2, 3)
    R = quats_to_rotmats(quats)
    rot_cam = Rw[None] @ R
    M = rot_cam * scales[:, None, :]
    cov_cam = M @ M.transpose(1, 2)
    JM = J @ cov_cam
    cov2d = JM @ J.transpose(1, 2)
    a = cov2d[:, 0, 0] + blur
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + blur
    det = (a * c - b * b).clamp_min(1e-12)
    s2 = support_sigmas * support_sigmas
    conics = torch.stack([c / det, -b / det, a / det], dim=-1) / s2
    means2d = torch.stack([fx * x / zc + cx, fy * y / zc + cy], dim=-1)
    with torch.no_grad():
        hx = support_sigmas * torch.sqrt(a)
        hy = support_sigmas * torch.sqrt(c)
        mx, my = means2d[:, 0], means2d[:, 1]
        visible = (
            (z > near)
            & (mx + hx > 0) & (mx - hx < width)
            & (my + hy > 0) & (my - hy < height)
            & torch.isfinite(means2d).all(-1)
        )
    return Projected(means2d, conics, z, visible, means_cam, rot_cam)
