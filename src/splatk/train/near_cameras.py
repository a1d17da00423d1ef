"""Primitives close to a train camera for their size.

EWA splatting projects a primitive with the first-order expansion of the perspective map at its
centre (paper Eq. 1). That holds while the primitive is small against its depth. A primitive whose
centre is nearer a camera than a few times its support radius is drawn far beyond its true
footprint there, and a new view beside that camera can draw it as a veil over the whole image
(issue #29: kangaroo's near test view, `benchmarks/near_camera_veils.py`).

A primitive is **close** to a camera when its centre is in front of it at a depth under
``CLOSE_SUPPORTS`` x its support radius: the kernel's support in sigmas x its largest scale, so that
kernels of different support (the Gaussian's 3 sigma, the learned kernel's 1) compare at the same
footprint. It **holds** a camera when the camera lies inside its support ellipsoid; on real
captures those are the backdrop round the capture, which the fitted views rest on (decision 0112),
so a primitive that holds a train camera never counts.
"""
from __future__ import annotations

import torch

from ..functional.projection import quats_to_rotmats
from ..models.volumetric import SplatModel

#: close: centre depth under this many support radii (the same mark as near_camera_veils.py's)
CLOSE_SUPPORTS = 3.0


@torch.no_grad()
def close_to_cameras(model, cameras) -> torch.Tensor:
    """[N] bool: the primitives close to one of ``cameras`` or more that hold none of them (all
    False for planar primitives, which have their own rules at the camera)."""
    means = model.prims["means"]
    mask = torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
    if not isinstance(model, SplatModel) or len(cameras) == 0:
        return mask
    scales = model.scales
    support = model.kernel.support_sigmas
    radius = support * scales.max(dim=1).values
    rotations = quats_to_rotmats(model.prims["quats"])
    holds = torch.zeros_like(mask)
    for cam in cameras:
        world_to_cam = cam.world_to_cam.to(means.device)
        depth = means @ world_to_cam[2, :3] + world_to_cam[2, 3]
        mask |= (depth > 0) & (depth < CLOSE_SUPPORTS * radius)
        # the camera centre in each primitive's frame, in its sigmas along the three axes
        offset = cam.center.to(means.device) - means
        local = torch.einsum("nji,nj->ni", rotations, offset) / scales
        holds |= (local * local).sum(dim=1) <= support * support
    return mask & ~holds
