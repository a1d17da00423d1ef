"""Planar (surfel) rasterisation by backend name: :meth:`Backend.rasterize_planar` of
``get(backend, device)``.

``torch`` is the dense pure-torch reference (:mod:`splatk.backends.planar_torch`, the
specification); ``cpu`` the native tiled rasteriser (:mod:`splatk.backends.planar_cpu`), same
values and gradients. ``auto`` picks ``cpu`` for CPU tensors when it builds, else ``torch``.
"""
from __future__ import annotations

import torch

from . import get
from .types import PLANAR_PROFILE_KINDS, PlanarProfile, RasterOutput


def rasterize_planar(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                     opacities: torch.Tensor, colors: torch.Tensor, viewmat: torch.Tensor,
                     K: torch.Tensor, width: int, height: int, profile: PlanarProfile,
                     background: torch.Tensor | None = None, backend: str = "auto") -> RasterOutput:
    """Composite planar splats into an image. Differentiable in every float input.

    Args:
        means, quats, scales: [N, 3], [N, 4] (w, x, y, z), [N, 2] disks.
        opacities: [N] in [0, 1]; colors: [N, C].
        viewmat, K: [4, 4] world->camera, [3, 3] intrinsics.
        width, height: image size.
        profile: :class:`PlanarProfile` (``gaussian_surfel`` or per-primitive ``grid`` tables).
        background: [C] or None (zeros).
        backend: ``torch``, ``cpu`` or ``auto``.
    """
    if profile.kind not in PLANAR_PROFILE_KINDS:
        raise ValueError(f"unknown planar profile {profile.kind!r}; choose from {', '.join(PLANAR_PROFILE_KINDS)}")
    return get(backend, means.device).rasterize_planar(means, quats, scales, opacities, colors, viewmat,
                                                        K, width, height, profile, background)


__all__ = ["PlanarProfile", "rasterize_planar"]
