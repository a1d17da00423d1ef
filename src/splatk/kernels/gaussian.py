"""The 3DGS Gaussian kernel exp(-m^2 / 2), truncated at 3 sigma."""
from __future__ import annotations

from ..backends import GAUSSIAN_SUPPORT_SIGMAS, Profile
from .base import Kernel, ViewContext, register_kernel


@register_kernel
class GaussianKernel(Kernel):
    name = "gaussian"
    support_sigmas = GAUSSIAN_SUPPORT_SIGMAS

    def profile(self, prims, view: ViewContext) -> Profile:
        return Profile("gaussian")
