"""The types and constants of the rasteriser contract (see :mod:`splatk.backends`): what kernels
hand a backend and what a backend returns."""
from __future__ import annotations

from typing import NamedTuple

import torch

GAUSSIAN_SUPPORT_SIGMAS = 3.0
STUDENT_T_SUPPORT_SIGMAS = 3.0
ALPHA_MAX = 0.999
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
TILE_SIZE = 16

PROFILE_KINDS = ("gaussian", "beta", "student_t", "table")


class Profile(NamedTuple):
    """Radial opacity profile handed to the rasteriser.

    Attributes:
        kind: one of ``PROFILE_KINDS``.
        params: ``None`` for gaussian; ``[N, 1]`` beta / nu; ``[N, k]`` table samples (k >= 2).
    """

    kind: str
    params: torch.Tensor | None = None


class RasterOutput(NamedTuple):
    """Rendered image.

    Attributes:
        colors: [H, W, C] composited colours (background included).
        alphas: [H, W, 1] accumulated opacity ``1 - T_final``.
    """

    colors: torch.Tensor
    alphas: torch.Tensor


PLANAR_PROFILE_KINDS = ("gaussian_surfel", "grid")


class PlanarProfile(NamedTuple):
    """Opacity profile over a planar splat's normalised (u, v) (support: the unit disk).

    Attributes:
        kind: ``gaussian_surfel`` (exp(-4.5 r^2), no parameters) or ``grid``.
        table: ``grid`` only: [N, G, G] values at nodes ``linspace(-1, 1, G)`` indexed [v, u]
            (bilinear, :func:`splatk.functional.planar.bilinear`), one table per primitive;
            gradients flow into it.
    """

    kind: str
    table: torch.Tensor | None = None
