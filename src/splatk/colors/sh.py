"""Spherical-harmonics colour (3DGS): sh0 [N, 1, 3] and sh_rest [N, (D+1)^2 - 1, 3]."""
from __future__ import annotations

import torch

from ..functional.sh import num_sh_bases, rgb_to_sh0
from .base import ColorModel, register_color_model


@register_color_model
class SHColor(ColorModel):
    name = "sh"

    def __init__(self, sh_degree: int = 3):
        self.sh_degree = sh_degree

    def init_primitive_params(self, rgb):
        n = rgb.shape[0]
        rest = num_sh_bases(self.sh_degree) - 1
        return {
            "sh0": rgb_to_sh0(rgb)[:, None, :].clone(),
            "sh_rest": torch.zeros(n, rest, 3, device=rgb.device),
        }

    def learning_rates(self):
        return {"sh0": 0.0025, "sh_rest": 0.0025 / 20}  # 3DGS-MCMC

    def colors(self, prims, dirs, degree, backend):
        return backend.sh_colors(prims["sh0"], prims["sh_rest"], dirs, min(degree, self.sh_degree))

    def base_rgb_params(self, prims):
        return prims["sh0"][:, 0, :], prims["sh_rest"]
