"""2DGS's two geometry terms for planar primitives: normal consistency and depth distortion.

2DGS (Huang et al. 2024, Sec. 4.2; peers.md Sec. 5) adds to the photometric loss
``lambda_normal (1 - n_render . n_surf)`` from iteration 7000 (lambda 0.05) and
``lambda_dist`` times a depth distortion from iteration 3000 (lambda 0 by default). Both are
computed here from what one rasteriser call composites (``PlanarModel.render(geometry=True)``:
normals, ``q`` and ``q q^T`` per surfel, :mod:`splatk.functional.surfel_depth`), so every backend
has them without a native op of its own.

With ``b_i`` a pixel's blending weights, ``A = sum_i b_i`` its alpha, ``E[x] = sum_i b_i x_i``
(not divided by ``A``) and ``w_i = 1/z_i`` the inverse depth where its ray meets surfel ``i``:

- depth distortion, per pixel ``A E[w^2] - E[w]^2 = 1/2 sum_ij b_i b_j (w_i - w_j)^2``: the squared
  form of 2DGS's ``sum_ij b_i b_j |m_i - m_j|``, whose NDC depth ``m`` is an affine map of ``1/z``
  (docs/decisions/0103-2dgs-regularisers.md says why the square);
- normal consistency, per pixel ``A - E[n] . N = sum_i b_i (1 - n_i . N)``, with ``N`` the normal
  of the depth map ``A / E[w]`` by central differences (2DGS's ``depth_to_normal``); pixels at
  the border or next to an uncovered one are left out.
"""
from __future__ import annotations

import torch

from ..functional.surfel_depth import inverse_depth_moments, pixel_rays

#: a pixel whose alpha is below this has no depth to speak of (its depth would be a few
#: near-transparent surfels' guess): it and its neighbours' normals are left out
COVERAGE_MIN = 0.01


def depth_distortion(geometry: torch.Tensor, alphas: torch.Tensor, rays: torch.Tensor) -> torch.Tensor:
    """Mean over pixels of the blended variance of inverse depth ``A E[1/z^2] - E[1/z]^2``.

    Args:
        geometry: [H, W, 12] blended surfel channels; alphas: [H, W, 1]; rays: [H, W, 3]
            (:func:`~splatk.functional.surfel_depth.pixel_rays`).
    """
    first, second = inverse_depth_moments(geometry, rays)
    return (alphas[..., 0] * second - first * first).mean()


def depth_normals(depth: torch.Tensor, rays: torch.Tensor) -> torch.Tensor:
    """[H - 2, W - 2, 3] unit normals of the camera-space surface ``depth * rays`` at the interior
    pixels, by central differences; they face the camera (2DGS's ``depth_to_normal``).

    Args:
        depth: [H, W] camera z; rays: [H, W, 3] with z = 1.
    """
    points = depth[..., None] * rays
    along_y = points[2:, 1:-1] - points[:-2, 1:-1]
    along_x = points[1:-1, 2:] - points[1:-1, :-2]
    # image y runs down and x right, so (d/dy x d/dx) points towards the camera (-z)
    return torch.nn.functional.normalize(torch.linalg.cross(along_y, along_x), dim=-1)


def normal_consistency(geometry: torch.Tensor, alphas: torch.Tensor, rays: torch.Tensor) -> torch.Tensor:
    """Mean over the interior covered pixels of ``A - E[n] . N`` (``N``: :func:`depth_normals` of
    the depth ``A / E[1/z]``); 0 when no pixel qualifies.

    Args:
        geometry: [H, W, 12] blended surfel channels; alphas: [H, W, 1]; rays: [H, W, 3].
    """
    a = alphas[..., 0]
    first, _ = inverse_depth_moments(geometry, rays)
    with torch.no_grad():
        covered = (a > COVERAGE_MIN) & (first > 0)
        valid = (covered[1:-1, 1:-1] & covered[2:, 1:-1] & covered[:-2, 1:-1]
                 & covered[1:-1, 2:] & covered[1:-1, :-2])
    # uncovered pixels get depth 1 with no gradient, not a division by ~0 (their normals are
    # left out, but a NaN in the graph would reach every gradient)
    depth = torch.where(covered, a / torch.where(covered, first, torch.ones_like(first)), torch.ones_like(a))
    normals = depth_normals(depth, rays)
    blended = geometry[1:-1, 1:-1, 0:3]
    per_pixel = a[1:-1, 1:-1] - (blended * normals).sum(-1)
    return (per_pixel * valid).sum() / valid.sum().clamp_min(1)


class GeometryTerms:
    """The two terms' weights and start iterations for one run (``TrainConfig``'s
    ``normal_weight``, ``normal_from``, ``distortion_weight``, ``distortion_from``). A term is on
    after its start iteration (as 2DGS: ``iteration > 7000``) when its weight is above 0; the
    trainer asks the model for the geometry channels only while one is on."""

    def __init__(self, normal_weight: float, normal_from: int, distortion_weight: float, distortion_from: int):
        self.normal_weight, self.normal_from = normal_weight, normal_from
        self.distortion_weight, self.distortion_from = distortion_weight, distortion_from

    def normal_on(self, it: int) -> bool:
        return self.normal_weight > 0 and it > self.normal_from

    def distortion_on(self, it: int) -> bool:
        return self.distortion_weight > 0 and it > self.distortion_from

    def wanted(self, it: int) -> bool:
        """Whether iteration ``it`` renders the geometry channels."""
        return self.normal_on(it) or self.distortion_on(it)

    def __call__(self, it: int, geometry: torch.Tensor, alphas: torch.Tensor,
                 K: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """(weighted sum of the terms that are on, {"normal_loss" / "distortion_loss": unweighted
        value}) for one rendered view (``K``: its [3, 3] intrinsics)."""
        height, width = alphas.shape[:2]
        rays = pixel_rays(K.to(device=alphas.device, dtype=alphas.dtype), width, height)
        loss, values = alphas.new_zeros(()), {}
        if self.normal_on(it):
            values["normal_loss"] = normal_consistency(geometry, alphas, rays)
            loss = loss + self.normal_weight * values["normal_loss"]
        if self.distortion_on(it):
            values["distortion_loss"] = depth_distortion(geometry, alphas, rays)
            loss = loss + self.distortion_weight * values["distortion_loss"]
        return loss, values
