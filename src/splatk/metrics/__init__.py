"""Image metrics as novel view synthesis papers report them: PSNR, SSIM (3DGS convention), LPIPS.

All take images in [0, 1] as [H, W, 3] or [B, 3, H, W] and return one value per image.
"""
from __future__ import annotations

from torch import Tensor

from .lpips import LPIPS, LPIPSWeightsMissing, lpips, lpips_available
from .psnr import psnr
from .ssim import ssim

__all__ = ["psnr", "ssim", "LPIPS", "lpips", "lpips_available", "LPIPSWeightsMissing",
           "compute_metrics", "METRICS"]

METRICS = ("psnr", "ssim", "lpips")


def compute_metrics(img: Tensor, ref: Tensor, metrics=METRICS, lpips_net: str = "alex",
                    mask: Tensor | None = None) -> dict:
    """Evaluation metrics of a render against its reference.

    ``img`` is clamped to [0, 1] for every metric (as 3DGS does before evaluating). For a batch
    each value is the mean of the per-image values.

    Args:
        img: [H, W, 3] or [B, 3, H, W] render, float.
        ref: same shape, ground truth in [0, 1].
        metrics: any of "psnr", "ssim", "lpips".
        lpips_net: "alex" or "vgg".
        mask: [H, W, 1] or [B, 1, H, W], 1 where a pixel counts (the dataset's mask; None: all).
            PSNR and SSIM average over those pixels only; LPIPS, whose network sees whole
            images, compares both images with the masked pixels set to 0.

    Returns:
        ``{name: float}`` for each requested metric. When LPIPS is requested but its weights
        are missing, ``"lpips"`` is None and ``"warnings"`` holds a message for the caller to
        print (the key is present only when there is something to say).
    """
    unknown = [m for m in metrics if m not in METRICS]
    if unknown:
        raise ValueError(f"unknown metric(s) {unknown}; choose from {list(METRICS)}")
    img = img.detach().clamp(0.0, 1.0)
    ref = ref.detach()
    out: dict = {}
    warnings: list[str] = []
    if "psnr" in metrics:
        out["psnr"] = float(psnr(img, ref, mask=mask).mean())
    if "ssim" in metrics:
        out["ssim"] = float(ssim(img, ref, mask=mask).mean())
    if "lpips" in metrics:
        if mask is not None:  # [H, W, 1] / [B, 1, H, W] broadcast over the channels
            img, ref = img * mask.to(img.dtype), ref * mask.to(ref.dtype)
        try:
            out["lpips"] = float(lpips(img, ref, net=lpips_net).mean())
        except LPIPSWeightsMissing as e:
            out["lpips"] = None
            warnings.append(str(e))
    if warnings:
        out["warnings"] = warnings
    return out
