"""Compare two image files with PSNR / SSIM / LPIPS (``splatk compare A B``).

Reading: OpenCV decodes the file, then it is read as scene loading reads a photo
(:func:`splatk.data._common.to_rgb`): 8-bit and 16-bit images are scaled to [0, 1], float images
clipped to it, BGR becomes RGB, a grey image is repeated to three channels and an alpha channel
is composited onto ``background``. So an RGBA pair scores here what `splatk fit` / `splatk eval`
measure on it with the same background (white for NeRF-synthetic / transforms scenes, black for
COLMAP scenes), up to the rounding to 8 bits per channel that scene loading stores (16-bit
files keep their precision here).

PSNR of identical images is infinite; ``"identical"`` says so without a float comparison.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..data._common import to_rgb
from ..errors import InputError
from ..metrics import METRICS, compute_metrics

#: what an alpha channel is composited on unless told: the NeRF-synthetic convention, which
#: scene loading uses for transforms scenes (the usual source of RGBA images)
DEFAULT_BACKGROUND = (1.0, 1.0, 1.0)


def read_rgb(path: str | Path, background=DEFAULT_BACKGROUND) -> np.ndarray:
    """Read an image file as float32 RGB in [0, 1], alpha composited onto ``background``.

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
    return to_rgb(im, path, background)


def compare_images(path_a: str | Path, path_b: str | Path, metrics=METRICS,
                   lpips_net: str = "alex", background=DEFAULT_BACKGROUND) -> dict:
    """Metrics of image ``path_a`` (the test image) against ``path_b`` (the reference).

    Args:
        path_a: image under test; clamped to [0, 1].
        path_b: reference image, same width and height.
        metrics: any of "psnr", "ssim", "lpips".
        lpips_net: "alex" or "vgg".
        background: RGB in [0, 1] that an alpha channel is composited onto.

    Returns:
        ``{"psnr", "ssim", "lpips"}`` (requested ones; ``lpips`` None when its weights are
        missing, with ``"warnings"``; ``psnr`` is ``inf`` for identical images), ``"identical"``
        (every measured value equal), ``"lpips_net"``, ``"background"`` and
        ``"size": [width, height]``.

    Raises:
        InputError: a file is missing or corrupt, or the sizes differ.
    """
    a = read_rgb(path_a, background)
    b = read_rgb(path_b, background)
    if a.shape != b.shape:
        raise InputError(path_b, f"size {b.shape[1]}x{b.shape[0]} differs from {path_a} "
                                 f"({a.shape[1]}x{a.shape[0]})",
                         "compare images of the same width and height")
    out = compute_metrics(torch.from_numpy(a), torch.from_numpy(b), metrics=metrics,
                          lpips_net=lpips_net)
    out["identical"] = bool(np.array_equal(a, b))
    out["lpips_net"] = lpips_net
    out["background"] = [float(v) for v in background]
    out["size"] = [int(a.shape[1]), int(a.shape[0])]
    return out
