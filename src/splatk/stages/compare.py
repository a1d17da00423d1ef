"""Compare two image files with PSNR / SSIM / LPIPS (``splatk compare A B``).

Reading: OpenCV decodes the file; 8-bit and 16-bit images are scaled to [0, 1], BGR becomes
RGB, a grey image is repeated to three channels and an alpha channel is *dropped* (not
composited on a background): the metrics compare the stored colour values, so save renders
of transparent scenes already composited on the background the reference uses.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..metrics import METRICS, compute_metrics


def read_rgb(path: str | Path) -> np.ndarray:
    """Read an image file as float32 RGB in [0, 1].

    Returns:
        [H, W, 3] float32.

    Raises:
        InputError: missing, unreadable or of an unsupported pixel type.
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "image file not found", "check the path")
    data = np.fromfile(str(path), dtype=np.uint8)
    im = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if im is None:
        raise InputError(path, "cannot be decoded as an image",
                         "give a valid PNG/JPEG/TIFF/EXR file; it may be truncated or corrupt")
    if im.dtype == np.uint8:
        scale = 255.0
    elif im.dtype == np.uint16:
        scale = 65535.0
    elif im.dtype in (np.float32, np.float64):
        scale = 1.0
    else:
        raise InputError(path, f"unsupported pixel type {im.dtype}", "save it as 8- or 16-bit PNG")
    if im.ndim == 2:
        im = np.repeat(im[:, :, None], 3, axis=2)
    elif im.shape[2] == 1:
        im = np.repeat(im, 3, axis=2)
    elif im.shape[2] == 4:
        im = im[:, :, :3]  # drop alpha, see module docstring
    elif im.shape[2] != 3:
        raise InputError(path, f"has {im.shape[2]} channels", "give an RGB or RGBA image")
    im = cv2.cvtColor(np.ascontiguousarray(im), cv2.COLOR_BGR2RGB)
    return (im.astype(np.float32) / np.float32(scale)).astype(np.float32)


def compare_images(path_a: str | Path, path_b: str | Path, metrics=METRICS,
                   lpips_net: str = "alex") -> dict:
    """Metrics of image ``path_a`` (the test image) against ``path_b`` (the reference).

    Args:
        path_a: image under test; clamped to [0, 1].
        path_b: reference image, same width and height.
        metrics: any of "psnr", "ssim", "lpips".
        lpips_net: "alex" or "vgg".

    Returns:
        ``{"psnr", "ssim", "lpips"}`` (requested ones; ``lpips`` None when its weights are
        missing, with ``"warnings"``), ``"lpips_net"`` and ``"size": [width, height]``.

    Raises:
        InputError: a file is missing or corrupt, or the sizes differ.
    """
    a = read_rgb(path_a)
    b = read_rgb(path_b)
    if a.shape != b.shape:
        raise InputError(path_b, f"size {b.shape[1]}x{b.shape[0]} differs from {path_a} "
                                 f"({a.shape[1]}x{a.shape[0]})",
                         "compare images of the same width and height")
    out = compute_metrics(torch.from_numpy(a), torch.from_numpy(b), metrics=metrics,
                          lpips_net=lpips_net)
    out["lpips_net"] = lpips_net
    out["size"] = [int(a.shape[1]), int(a.shape[0])]
    return out
