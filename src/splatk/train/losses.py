"""Training loss of DBS / 3DGS-MCMC: 0.8 L1 + 0.2 (1 - SSIM) + opacity and scale regularisers."""
from __future__ import annotations

import torch

from ..backends import Backend


def photometric_loss(image: torch.Tensor, target: torch.Tensor, backend: Backend,
                     lambda_dssim: float = 0.2) -> torch.Tensor:
    """image, target: [H, W, 3]; the SSIM term is ``backend.ssim`` (the render's backend)."""
    l1 = (image - target).abs().mean()
    if lambda_dssim <= 0:
        return l1
    s = backend.ssim(image, target.detach())
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - s)


def regularisers(model, opacity_reg: float, scale_reg: float) -> torch.Tensor:
    loss = torch.zeros((), device=model.prims["means"].device)
    if opacity_reg > 0:
        loss = loss + opacity_reg * model.opacities.abs().mean()
    if scale_reg > 0:
        loss = loss + scale_reg * model.scales.abs().mean()
    return loss
