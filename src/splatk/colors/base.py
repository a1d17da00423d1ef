"""Colour models: per-primitive appearance parameters -> RGB for a viewing direction."""
from __future__ import annotations

import torch

from ..backends import Backend


class ColorModel:
    """Base class. ``init_primitive_params`` gives raw per-primitive tensors (first dim N)."""

    name = "base"

    def init_primitive_params(self, rgb: torch.Tensor) -> dict[str, torch.Tensor]:
        """Initial parameters for primitives whose base colour is ``rgb`` [N, 3] in [0, 1]."""
        raise NotImplementedError

    def learning_rates(self) -> dict[str, float]:
        raise NotImplementedError

    def colors(self, prims: dict[str, torch.Tensor], dirs: torch.Tensor, degree: int,
               backend: Backend) -> torch.Tensor:
        """[M, 3] RGB of the visible primitives seen along ``dirs`` [M, 3] (camera -> mean).
        ``degree`` is the active SH degree (raised during training); ``backend`` the render's
        backend, whose ops (e.g. :meth:`Backend.sh_colors`) a colour model may use."""
        raise NotImplementedError

    def base_rgb_params(self, prims) -> dict[str, torch.Tensor]:
        """(f_dc [N, 3], f_rest [N, B, 3]) for a 3DGS PLY export."""
        raise NotImplementedError


COLOR_MODELS: dict[str, type[ColorModel]] = {}


def register_color_model(cls):
    COLOR_MODELS[cls.name] = cls
    return cls
