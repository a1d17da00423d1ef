"""The learned kernel drawn as a plain Gaussian, for 3DGS viewers (``splatk export``)."""
from __future__ import annotations

import torch

from ..functional.projection import quats_to_rotmats
from .base import ViewContext


def canonical_views(n_views: int = 6) -> torch.Tensor:
    """[V, 3, 3] world->camera rotations looking along +-x, +-y, +-z (first ``n_views``)."""
    rots = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            f = torch.zeros(3)
            f[axis] = sign
            up = torch.zeros(3)
            up[(axis + 1) % 3] = 1.0
            r = torch.linalg.cross(f, up)
            d = torch.linalg.cross(f, r)
            rots.append(torch.stack([r, d, f]))
    return torch.stack(rots[:n_views])


@torch.no_grad()
def gaussian_scale_factor(kernel, prims, n_views: int = 6, depth_over_scale: float = 100.0,
                          chunk: int = 65536) -> torch.Tensor:
    """Per-primitive f such that a Gaussian of scale ``f * s`` has the second moment of the
    view-averaged kernel (for 3DGS viewers, which cannot show view dependence).

    Approximation: the view-dependent kernel is averaged over ``n_views`` canonical views
    (the camera looks along +-x, +-y, +-z of the world at the primitive, centred on the
    optical axis at a depth of ``depth_over_scale`` times its largest scale, i.e. a splat
    of a few pixels' radius). Its k-sample table is interpolated as the rasteriser does
    and, for the radially symmetric profile d(r) (r in units of the 1-sigma support), the
    matching Gaussian exp(-r^2 / (2 f^2)) has per-axis variance
    ``f^2 = int d r^3 dr / (2 int d r dr)``. The centre value d(0) is not carried over:
    viewers multiply the Gaussian by the stored opacity.
    """
    n = prims["means"].shape[0]
    views = canonical_views(n_views).to(prims["means"].device)
    grid = torch.linspace(0.0, 1.0, 257, device=views.device)
    out = torch.empty(n, device=views.device)
    for a in range(0, n, chunk):
        b = min(n, a + chunk)
        scales = torch.exp(prims["log_scales"][a:b])
        R = quats_to_rotmats(prims["quats"][a:b])
        depth = depth_over_scale * scales.amax(1)
        mu = torch.zeros(b - a, 3, device=views.device)
        mu[:, 2] = depth
        z3d = prims["z3d"][a:b] if "z3d" in prims else None
        tables = 0.0
        for V in views:
            view = ViewContext(mu, scales, V[None] @ R)
            tables = tables + kernel.samples(kernel.project(z3d, view))
        tables = tables / len(views)  # [m, k]
        # the rendered profile: linear interpolation of the table in r
        t = grid * (kernel.k - 1)
        idx = t.floor().long().clamp(0, kernel.k - 2)
        lam = t - idx
        d = (1 - lam) * tables[:, idx] + lam * tables[:, idx + 1]  # [m, G]
        num = torch.trapezoid(d * grid**3, grid, dim=1)
        den = torch.trapezoid(d * grid, grid, dim=1).clamp_min(1e-12)
        out[a:b] = torch.sqrt((num / (2 * den)).clamp_min(1e-8))
    return out
