"""Deformable Beta kernel (DBS): (1 - r^2)^beta inside the 1-sigma ellipse, beta = 4 exp(b)."""
from __future__ import annotations

import torch

from ..backends import Profile
from .base import Kernel, ViewContext, register_kernel


@register_kernel
class BetaKernel(Kernel):
    name = "beta"
    support_sigmas = 1.0

    def init_primitive_params(self, n, device):
        return {"beta_raw": torch.zeros(n, 1, device=device)}  # beta = 4 at init (DBS)

    def learning_rates(self):
        return {"beta_raw": 0.001}  # DBS beta_lr

    def profile(self, prims, view: ViewContext) -> Profile:
        return Profile("beta", 4.0 * torch.exp(prims["beta_raw"]))

    def gaussian_scale_factor(self, prims):
        # the Gaussian with the profile's second moment: over the unit disk, (1 - m^2)^beta has
        # E[m^2] = 1 / (beta + 2), so each axis has s^2 = 1 / (2 (beta + 2)). Matching the curvature at
        # the centre instead (s^2 = 1 / (2 beta)) fits the core and misses the shoulders, which
        # carry most of a low-beta splat's weight.
        beta = 4.0 * torch.exp(prims["beta_raw"][:, 0])
        return torch.rsqrt(2.0 * (beta + 2.0))
