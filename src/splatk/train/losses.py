"""Training loss of DBS / 3DGS-MCMC: 0.8 L1 + 0.2 (1 - SSIM) + opacity and scale regularisers."""
from __future__ import annotations

import torch

from ..backends import Backend


def photometric_loss(image: torch.Tensor, target: torch.Tensor, backend: Backend,
                     lambda_dssim: float = 0.2, mask: torch.Tensor | None = None) -> torch.Tensor:
    """image, target: [H, W, 3]; the SSIM term is ``backend.ssim`` (the render's backend).

    ``mask``: [H, W, 1], 1 where the pixel counts and 0 where the dataset masks it out. Both
    images are multiplied by it before the L1 and SSIM terms (nerfstudio's splatfacto), so a
    masked pixel adds nothing to the loss and passes no gradient to the render.
    """
    if mask is not None:
        image, target = image * mask, target * mask
    l1 = (image - target).abs().mean()
    if lambda_dssim <= 0:
        return l1
    s = backend.ssim(image, target.detach())
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - s)


def masked_mse(image: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None) -> float:
    """Mean squared error over the pixels that count (``mask`` [H, W, 1], None: all)."""
    if mask is None:
        return float(((image - target) ** 2).mean())
    kept = float(mask.sum()) * image.shape[-1]
    return float((((image - target) ** 2) * mask).sum()) / max(kept, 1.0)


def regularisers(model, opacity_reg: float, scale_reg: float) -> torch.Tensor:
    loss = torch.zeros((), device=model.prims["means"].device)
    if opacity_reg > 0:
        loss = loss + opacity_reg * model.opacities.abs().mean()
    if scale_reg > 0:  # times the kernel's weight: its footprint per unit scale (kernels.base)
        loss = loss + scale_reg * model.kernel.scale_reg_weight * model.scales.abs().mean()
    return loss
