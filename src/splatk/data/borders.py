"""Black borders: edge rows and columns that are black in every image of a scene.

Video frames padded to a coded size (1080 lines stored as 1088), letterboxing and some exports
leave a band of black along an image edge. It is the same in every view, so it is not the
scene: a model that fits it spends primitives on a black line that follows the camera, and a
test view scores mostly on where that line lands (juicebox's black last row moved its test views
by 0.4-8 dB, decision 0114). splatk leaves such a band out of the training loss and the metrics,
as a dataset mask would, and says so in the scene's warnings.

A row is black when its mean, over its pixels and channels, is at most :data:`BLACK` in every
image. The band is the run of black rows from the edge, and one row more: a resize (the
dataset's own or ``--downscale``) blends the band's last row into its neighbour, which is then
neither black nor the scene (juicebox's row beside the black one is at 0.49 where the rows above
are at 0.70). A band wider than :data:`MAX_FRACTION` of the image is not a border, and is left in.
Images are grouped by size, so a scene whose views have different sizes gets a band per size.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

#: a row or column is black when its mean (0-1, over pixels and channels) is at most this in
#: every image: 8 of 255 leaves room for a JPEG's ringing, and no lit scene is that dark on average
BLACK = 8.0 / 255.0
#: a band wider than this fraction of the image is the scene (a dark room), not a border
MAX_FRACTION = 1.0 / 8.0
EDGES = ("top", "bottom", "left", "right")


@dataclass(frozen=True)
class EdgeMeans:
    """Mean brightness of an image's outer rows and columns, from the edge inwards."""

    width: int
    height: int
    top: np.ndarray
    bottom: np.ndarray
    left: np.ndarray
    right: np.ndarray


def edge_means(image: np.ndarray) -> EdgeMeans:
    """:class:`EdgeMeans` of an [H, W, C] uint8 image: on each side, the outer
    :data:`MAX_FRACTION` of its rows (columns) and two more, enough to see a band end."""
    h, w = image.shape[:2]
    rows = image.reshape(h, -1).mean(1) / 255.0
    cols = image.transpose(1, 0, 2).reshape(w, -1).mean(1) / 255.0
    nr, nc = int(h * MAX_FRACTION) + 2, int(w * MAX_FRACTION) + 2
    return EdgeMeans(width=w, height=h, top=rows[:nr], bottom=rows[::-1][:nr], left=cols[:nc], right=cols[::-1][:nc])


def black_band(means: list[EdgeMeans]) -> dict[str, int]:
    """Rows (top, bottom) and columns (left, right) to leave out along each edge of images of
    one size: the run of rows black in every image, plus the blended row beside it; 0 without
    a black edge row."""
    band = {}
    for edge in EDGES:
        brightest = np.max(np.stack([getattr(m, edge) for m in means]), axis=0)  # over the images, per row
        size = means[0].height if edge in ("top", "bottom") else means[0].width
        lit = brightest > BLACK
        black = int(np.argmax(lit)) if lit.any() else len(brightest)  # black rows from the edge in
        band[edge] = black + 1 if black > 0 and black + 1 <= size * MAX_FRACTION else 0
    return band


def band_mask(band: dict[str, int], width: int, height: int, out_width: int, out_height: int) -> np.ndarray:
    """[out_height, out_width] bool, False on every output pixel that any band pixel of the
    ``width`` x ``height`` image falls into (area resampling, so a mixed pixel is left out)."""
    keep = np.ones((height, width), np.float32)
    keep[:band["top"]] = 0
    keep[height - band["bottom"]:] = 0
    keep[:, :band["left"]] = 0
    keep[:, width - band["right"]:] = 0
    if (width, height) != (out_width, out_height):
        keep = cv2.resize(keep, (out_width, out_height), interpolation=cv2.INTER_AREA)
    return keep >= 1.0 - 1e-6


def mask_black_bands(cams: list, means: list[EdgeMeans | None], warnings: list[str]) -> None:
    """Leave each image size's black band out of its cameras' masks (in place), with a warning
    naming the band."""
    by_size: dict[tuple[int, int], list[int]] = {}
    for i, m in enumerate(means):
        if m is not None:
            by_size.setdefault((m.width, m.height), []).append(i)
    for (w, h), idx in sorted(by_size.items()):
        band = black_band([means[i] for i in idx])
        if not any(band.values()):
            continue
        for i in idx:
            cam = cams[i]
            keep = torch.from_numpy(band_mask(band, w, h, cam.width, cam.height))
            cam.mask = keep if cam.mask is None else cam.mask & keep
        where = ", ".join(f"{band[e]} {'row' if e in ('top', 'bottom') else 'column'}"
                          f"{'s' if band[e] > 1 else ''} at the {e}" for e in EDGES if band[e])
        warnings.append(f"{len(idx)} images of {w}x{h} are black along an edge ({where}, counting the row "
                        "a resize blends with it); those pixels are left out of training and metrics")
