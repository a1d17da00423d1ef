"""Structural similarity (SSIM, Wang et al. 2004), as 3DGS reports it.

Convention (the one this field's papers report): the 3DGS ``ssim()`` in
``utils/loss_utils.py`` of graphdeco-inria/gaussian-splatting. An 11x11 Gaussian window,
sigma 1.5, normalised to sum 1; local statistics by ``conv2d`` with ``padding=window // 2``,
i.e. *zero padding* ('same' output size); C1 = 0.01^2, C2 = 0.03^2 (data range 1); the SSIM
map averaged over every pixel and channel. RGB channels are treated independently (no
conversion to grey).

``padding="valid"`` gives the other common convention: only windows fully inside the image,
which is what torchmetrics' ``structural_similarity_index_measure`` returns (it reflect-pads
and then crops ``window // 2`` pixels from every side of the map) and what gsplat's
``simple_trainer`` reports at eval time. The two agree in the interior; 'same' scores the
border windows against zeros, so it is slightly lower on textured borders and the gap
shrinks as the image grows (about ``2 * (window // 2) / min(H, W)`` of the pixels).

Differentiable (it is also the D-SSIM term of the training loss). Inputs are not clamped,
so gradients flow for renders that overshoot [0, 1]; clamp before calling for evaluation.
The 2-D Gaussian is separable, so each local statistic is two 1-D ``conv2d`` passes
(``groups=channels``) over the five stacked maps x, y, x^2, y^2, xy.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from .psnr import as_bchw, check_pair

C1 = 0.01**2
C2 = 0.03**2


def gaussian_window(window_size: int, sigma: float, dtype=torch.float32, device=None) -> Tensor:
    """1-D Gaussian taps ``exp(-(x - window_size // 2)^2 / (2 sigma^2))``, normalised to sum 1.

    Returns:
        [window_size]
    """
    if window_size < 1 or window_size % 2 == 0:
        raise ValueError(f"window_size must be a positive odd integer, got {window_size}")
    centre = window_size // 2
    taps = [math.exp(-((i - centre) ** 2) / (2.0 * sigma**2)) for i in range(window_size)]
    g = torch.tensor(taps, dtype=torch.float64)
    return (g / g.sum()).to(dtype=dtype, device=device)


def _blur(x: Tensor, g: Tensor, pad: int) -> Tensor:
    """Separable Gaussian filter of every channel: x [N, C, H, W] -> [N, C, H', W']."""
    c = x.shape[1]
    k = g.numel()
    x = F.conv2d(x, g.view(1, 1, 1, k).expand(c, 1, 1, k), padding=(0, pad), groups=c)
    return F.conv2d(x, g.view(1, 1, k, 1).expand(c, 1, k, 1), padding=(pad, 0), groups=c)


def ssim_map(img: Tensor, ref: Tensor, window_size: int = 11, sigma: float = 1.5,
             padding: str = "same") -> Tensor:
    """Per-pixel SSIM map (paper Eq. 13 with Gaussian-weighted local statistics, Eq. 14-16).

    Args:
        img: [B, C, H, W]
        ref: [B, C, H, W]
        padding: "same" (zero padding, 3DGS) or "valid" (full windows only, torchmetrics).

    Returns:
        [B, C, H, W] for "same", [B, C, H - window_size + 1, W - window_size + 1] for "valid".
    """
    if padding not in ("same", "valid"):
        raise ValueError(f"padding must be 'same' or 'valid', got {padding!r}")
    pad = window_size // 2 if padding == "same" else 0
    if padding == "valid" and min(img.shape[-2:]) < window_size:
        raise ValueError(f"'valid' SSIM needs images of at least {window_size}x{window_size}, "
                         f"got {tuple(img.shape[-2:])}")
    g = gaussian_window(window_size, sigma, dtype=img.dtype, device=img.device)
    b = img.shape[0]
    stats = _blur(torch.cat([img, ref, img * img, ref * ref, img * ref], dim=0), g, pad)
    mu_x, mu_y, e_xx, e_yy, e_xy = stats.split(b, dim=0)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    var_x, var_y, cov_xy = e_xx - mu_xx, e_yy - mu_yy, e_xy - mu_xy
    num = (2.0 * mu_xy + C1) * (2.0 * cov_xy + C2)
    den = (mu_xx + mu_yy + C1) * (var_x + var_y + C2)
    return num / den


def ssim(img: Tensor, ref: Tensor, window_size: int = 11, sigma: float = 1.5,
         padding: str = "same", mask: Tensor | None = None) -> Tensor:
    """Mean SSIM of each image (3DGS convention by default, see the module docstring).

    Args:
        img: [H, W, C] or [B, C, H, W], float, data range 1.
        ref: same shape as ``img``.
        window_size: odd side of the Gaussian window.
        sigma: standard deviation of the Gaussian window in pixels.
        padding: "same" (3DGS, reported) or "valid" (torchmetrics).
        mask: [H, W, 1] or [B, 1, H, W], 1 where a pixel counts (None: all): the SSIM map is
            averaged over those pixels only, after both images are set to 0 where masked (so
            masked content does not reach the windows of the pixels that count).

    Returns:
        0-d tensor for an [H, W, C] input, [B] for a batch (mean over channels and pixels).
        For the training loss use ``1 - ssim(...).mean()``.
    """
    check_pair(img, ref)
    x, single = as_bchw(img)
    y, _ = as_bchw(ref)
    if mask is None:
        out = ssim_map(x, y, window_size, sigma, padding).flatten(1).mean(1)
    else:
        m = as_bchw(mask)[0].to(x.dtype)
        smap = ssim_map(x * m, y * m, window_size, sigma, padding)
        if padding == "valid":
            cut = window_size // 2
            m = m[..., cut:m.shape[-2] - cut, cut:m.shape[-1] - cut]
        m = m.expand_as(smap)
        out = (smap * m).flatten(1).sum(1) / m.flatten(1).sum(1).clamp_min(1.0)
    return out[0] if single else out
