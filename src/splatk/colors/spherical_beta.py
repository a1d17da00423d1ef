"""Spherical Beta colour (DBS, peers.md 1.2): a diffuse SH-0 base plus L specular lobes

    color = max(0.2821 * sh0 + 0.5, 0) + sum_i c_i * max(<d, mu_i>, 0) ^ (4 exp(b_i))

with mu_i = (sin t cos p, sin t sin p, cos t), lobe colours softplus(x, beta = 10 ln 2)."""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..functional.sh import SH_C0, rgb_to_sh0
from .base import ColorModel, register_color_model


@register_color_model
class SphericalBetaColor(ColorModel):
    name = "sb"

    def __init__(self, num_lobes: int = 2, sh_degree: int = 0):
        self.num_lobes = num_lobes

    def init_primitive_params(self, rgb):
        n = rgb.shape[0]
        dev = rgb.device
        lobes = torch.zeros(n, self.num_lobes, 6, device=dev)
        lobes[..., 3] = torch.rand(n, self.num_lobes, device=dev) * math.pi
        lobes[..., 4] = torch.rand(n, self.num_lobes, device=dev) * 2 * math.pi
        return {"sh0": rgb_to_sh0(rgb)[:, None, :].clone(), "sb_lobes": lobes}

    def learning_rates(self):
        return {"sh0": 0.0025, "sb_lobes": 0.0025}  # DBS sb_params_lr

    def colors(self, prims, dirs, degree, backend):
        base = (SH_C0 * prims["sh0"][:, 0, :] + 0.5).clamp_min(0.0)
        lobes = prims["sb_lobes"]
        theta, phi = lobes[..., 3], lobes[..., 4]
        mu = torch.stack(
            [torch.sin(theta) * torch.cos(phi), torch.sin(theta) * torch.sin(phi), torch.cos(theta)], -1
        )
        d = F.normalize(dirs, dim=-1)
        cos = (mu * d[:, None, :]).sum(-1).clamp_min(0.0)
        sharp = 4.0 * torch.exp(lobes[..., 5])
        # cos^sharp via exp(sharp * log cos); cos == 0 -> 0 (guarded log keeps gradients finite)
        w = torch.where(cos > 0, torch.exp(sharp * torch.log(cos.clamp_min(1e-12))), torch.zeros_like(cos))
        lobe_rgb = F.softplus(lobes[..., :3], beta=10 * math.log(2))
        return (base + (w[..., None] * lobe_rgb).sum(1)).clamp_min(0.0)

    def base_rgb_params(self, prims):
        n = prims["sh0"].shape[0]
        return prims["sh0"][:, 0, :], torch.zeros(n, 0, 3, device=prims["sh0"].device)
