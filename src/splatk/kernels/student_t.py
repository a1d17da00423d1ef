"""Student's t kernel (SSS, positive opacities only): (1 + m^2 / nu)^(-(nu + 2) / 2),
truncated at 3 sigma. nu = 1 + softplus(raw) keeps it in (1, inf); init nu ~ 5."""
from __future__ import annotations

import torch
import torch.nn.functional as F

from ..backends import STUDENT_T_SUPPORT_SIGMAS, Profile
from .base import Kernel, ViewContext, register_kernel


@register_kernel
class StudentTKernel(Kernel):
    name = "student_t"
    support_sigmas = STUDENT_T_SUPPORT_SIGMAS

    def init_primitive_params(self, n, device):
        raw0 = torch.log(torch.expm1(torch.tensor(4.0)))  # nu = 5
        return {"nu_raw": torch.full((n, 1), float(raw0), device=device)}

    def learning_rates(self):
        return {"nu_raw": 0.01}

    def profile(self, prims, view: ViewContext) -> Profile:
        return Profile("student_t", 1.0 + F.softplus(prims["nu_raw"]))
