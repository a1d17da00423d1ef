"""The ``torch`` backend: pure PyTorch on any device, the specification the others are tested
against. It composes :mod:`splatk.functional` (projection, SH), :mod:`splatk.metrics.ssim` and
the reference rasterisers (:mod:`.torch_ref`, :mod:`.planar_torch`)."""
from __future__ import annotations

import torch

from ..functional.projection import Projected, project_ellipsoids
from ..functional.sh import eval_sh
from ..metrics.ssim import ssim
from .base import Backend
from .planar_torch import rasterize_planar
from .registry import register_backend
from .torch_ref import rasterize_torch
from .types import PlanarProfile, Profile, RasterOutput


@register_backend("torch")
class TorchBackend(Backend):
    """Runs everywhere; autograd differentiates every op."""

    priority = 0

    def project(self, means, quats, scales, viewmat, K, width, height, support_sigmas=3.0,
                want_view=False) -> Projected:
        return project_ellipsoids(means, quats, scales, viewmat, K, width, height,
                                  support_sigmas=support_sigmas)

    def sh_colors(self, sh0, sh_rest, dirs, degree) -> torch.Tensor:
        return eval_sh(torch.cat([sh0, sh_rest], dim=1), dirs, degree)

    def rasterize(self, means2d, conics, opacities, colors, depths, profile: Profile, width, height,
                  background) -> RasterOutput:
        return rasterize_torch(means2d, conics, opacities, colors, depths, profile, int(width),
                               int(height), background)

    def rasterize_planar(self, means, quats, scales, opacities, colors, viewmat, K, width, height,
                         profile: PlanarProfile, background=None) -> RasterOutput:
        return rasterize_planar(means, quats, scales, opacities, colors, viewmat, K, width, height,
                                profile, background)

    def ssim(self, img, ref) -> torch.Tensor:
        return ssim(img.permute(2, 0, 1)[None], ref.permute(2, 0, 1)[None]).mean()
