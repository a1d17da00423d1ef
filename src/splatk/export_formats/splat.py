"""antimatter15's ``.splat`` (the web viewers' format): no header, 32 bytes per Gaussian,
little-endian:

====== ============= ==================================================================
bytes  type          value
====== ============= ==================================================================
0-11   float32 x 3   position
12-23  float32 x 3   scale (linear: exp of the PLY's log scale)
24-27  uint8 x 4     colour R G B = 255 (0.5 + SH_C0 f_dc), A = 255 sigmoid(opacity)
28-31  uint8 x 4     unit quaternion (w, x, y, z) as q * 128 + 128
====== ============= ==================================================================

Rows are sorted by descending ``scale_x scale_y scale_z * opacity``, as the viewer's converter
does (it draws the first rows first while the file streams in). The format has one colour per
Gaussian: spherical-harmonic bands above the DC term are not stored.
"""
from __future__ import annotations

from typing import BinaryIO

import numpy as np

from ..functional.sh import SH_C0
from .gaussians import Gaussians

#: one row of a .splat file
SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])


def _to_uint8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


def splat_rows(gaussians: Gaussians) -> np.ndarray:
    """The file's rows (:data:`SPLAT_DTYPE`), in the file's order."""
    g = gaussians
    opacities = 1.0 / (1.0 + np.exp(-g.opacity_logits.astype(np.float64)))
    order = np.argsort(-np.exp(g.log_scales.astype(np.float64).sum(1)) * opacities, kind="stable")
    rows = np.empty(len(g), SPLAT_DTYPE)
    rows["position"] = g.means
    rows["scale"] = np.exp(g.log_scales)
    rows["rgba"][:, :3] = _to_uint8((0.5 + SH_C0 * g.sh0) * 255)
    rows["rgba"][:, 3] = _to_uint8(opacities * 255)
    quats = g.quats / np.linalg.norm(g.quats, axis=1, keepdims=True)
    rows["rot"] = _to_uint8(quats * 128 + 128)
    return rows[order]


def write_splat(gaussians: Gaussians, f: BinaryIO) -> None:
    f.write(splat_rows(gaussians).tobytes())
