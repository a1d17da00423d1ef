"""The 3DGS PLY: one binary little-endian ``vertex`` element of float32 columns
x y z nx ny nz f_dc_* f_rest_* opacity scale_* rot_* (raw, pre-activation values), as Inria's
3DGS writes it and common viewers read it."""
from __future__ import annotations

from typing import BinaryIO

import numpy as np

from .gaussians import Gaussians


def ply_arrays(gaussians: Gaussians) -> dict[str, np.ndarray]:
    """Named float32 columns of a 3DGS PLY, in the file's order."""
    n = len(gaussians)
    f_rest = gaussians.sh_rest.transpose(0, 2, 1).reshape(n, -1)  # channel-major, as 3DGS writes it
    cols: dict[str, np.ndarray] = {}
    for i, a in enumerate("xyz"):
        cols[a] = gaussians.means[:, i]
    for a in ("nx", "ny", "nz"):
        cols[a] = np.zeros(n, np.float32)
    for i in range(3):
        cols[f"f_dc_{i}"] = gaussians.sh0[:, i]
    for i in range(f_rest.shape[1]):
        cols[f"f_rest_{i}"] = f_rest[:, i]
    cols["opacity"] = gaussians.opacity_logits
    for i in range(3):
        cols[f"scale_{i}"] = gaussians.log_scales[:, i]
    for i in range(4):
        cols[f"rot_{i}"] = gaussians.quats[:, i]
    return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in cols.items()}


def write_ply(gaussians: Gaussians, f: BinaryIO) -> None:
    from plyfile import PlyData, PlyElement

    cols = ply_arrays(gaussians)
    arr = np.empty(len(gaussians), dtype=[(k, "f4") for k in cols])
    for k, v in cols.items():
        arr[k] = v
    PlyData([PlyElement.describe(arr, "vertex")]).write(f)
