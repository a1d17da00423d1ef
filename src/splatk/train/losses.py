"""Training loss of DBS / 3DGS-MCMC: 0.8 L1 + 0.2 (1 - SSIM) + opacity and scale regularisers."""
from __future__ import annotations

import torch

from ..metrics.ssim import ssim


def photometric_loss(image: torch.Tensor, target: torch.Tensor, lambda_dssim: float = 0.2,
                     fused: bool = False) -> torch.Tensor:
    """image, target: [H, W, 3]. ``fused``: the native SSIM (same value, one pass)."""
    l1 = (image - target).abs().mean()
    if lambda_dssim <= 0:
        return l1
    if fused:
        from ..backends.fused_cpu import ssim_mean_fused

        s = ssim_mean_fused(image, target.detach())
    else:
        s = ssim(image.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]).mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - s)


def regularisers(model, opacity_reg: float, scale_reg: float) -> torch.Tensor:
    loss = torch.zeros((), device=model.prims["means"].device)
    if opacity_reg > 0:
        loss = loss + opacity_reg * model.opacities.abs().mean()
    if scale_reg > 0:
        loss = loss + scale_reg * model.scales.abs().mean()
    return loss
