"""Peak signal-to-noise ratio."""
from __future__ import annotations

import torch
from torch import Tensor


def as_bchw(img: Tensor) -> tuple[Tensor, bool]:
    """Bring an image to [B, C, H, W].

    Args:
        img: [H, W, C] (channels last, C <= 4) or [B, C, H, W].

    Returns:
        (images [B, C, H, W], whether the input was a single [H, W, C] image).
    """
    if img.dim() == 3:
        if img.shape[-1] > 4:
            raise ValueError(f"expected an [H, W, C] image with C <= 4, got shape {tuple(img.shape)}")
        return img.permute(2, 0, 1).unsqueeze(0), True
    if img.dim() == 4:
        return img, False
    raise ValueError(f"expected [H, W, C] or [B, C, H, W], got shape {tuple(img.shape)}")


def check_pair(img: Tensor, ref: Tensor) -> None:
    if img.shape != ref.shape:
        raise ValueError(f"image shape {tuple(img.shape)} differs from reference shape {tuple(ref.shape)}")


def psnr(img: Tensor, ref: Tensor, mask: Tensor | None = None) -> Tensor:
    """PSNR in dB with data range 1: ``-10 log10(MSE)``.

    ``img`` is clamped to [0, 1] first (a render may overshoot); ``ref`` is taken as it is.
    The MSE is over all pixels and channels of each image, so a batch gives one value per
    image (the per-image convention of 3DGS/gsplat evaluation; average those for a scene).

    Args:
        img: [H, W, 3] or [B, 3, H, W], float in [0, 1].
        ref: same shape as ``img``.
        mask: [H, W, 1] or [B, 1, H, W], 1 where a pixel counts (None: all): the MSE is over
            those pixels only.

    Returns:
        0-d tensor for an [H, W, 3] input, [B] for a batch. ``inf`` where the images are equal.
    """
    check_pair(img, ref)
    x, single = as_bchw(img)
    y, _ = as_bchw(ref)
    err = (x.clamp(0.0, 1.0) - y).square()
    if mask is None:
        mse = err.flatten(1).mean(1)
    else:
        m = as_bchw(mask)[0].to(err.dtype)
        mse = (err * m).flatten(1).sum(1) / (m.flatten(1).sum(1) * err.shape[1]).clamp_min(1.0)
    out = -10.0 * torch.log10(mse)
    return out[0] if single else out
