"""Point clouds from PLY files: a nerfstudio dataset's ``ply_file_path`` (its SfM points).

nerfstudio writes them (``ns-process-data``, ``colmap_utils.create_ply_from_colmap``) as a
``vertex`` element with float ``x, y, z`` and uchar ``red, green, blue``, already in the frame of
the transforms file's camera poses, so the points are used as they are.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import plyfile

from ..errors import InputError
from .cameras import FLOAT32_SAFE

#: colour of points whose PLY has no colour properties (mid grey)
DEFAULT_GREY = 0.5


def read_ply_points(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(xyz [P, 3] float64, rgb [P, 3] float64 in [0, 1]) of the ``vertex`` element of a PLY file.

    Colours are ``red, green, blue`` (uchar: / 255, float: as they are) or grey when absent.

    Raises:
        InputError: naming ``path``, when it is missing, not a PLY file, has no vertices with
            x, y, z, or a position that is not finite.
    """
    fix = "re-export the point cloud (ns-process-data writes it), or remove ply_file_path to start from random points"
    if not path.is_file():
        raise InputError(path, "point cloud named by ply_file_path does not exist", fix)
    try:
        ply = plyfile.PlyData.read(str(path))
        vertex = ply["vertex"]
        names = vertex.data.dtype.names or ()
        if not all(c in names for c in "xyz"):
            raise KeyError("x, y, z")
        xyz = np.stack([np.asarray(vertex[c], dtype=np.float64) for c in "xyz"], axis=1)
        if all(c in names for c in ("red", "green", "blue")):
            channels = [np.asarray(vertex[c]) for c in ("red", "green", "blue")]
            scale = 255.0 if channels[0].dtype.kind in "ui" else 1.0
            rgb = np.clip(np.stack(channels, axis=1).astype(np.float64) / scale, 0.0, 1.0)
        else:
            rgb = np.full_like(xyz, DEFAULT_GREY)
    except KeyError as e:
        raise InputError(path, f"PLY file has no vertex element with {e.args[0] if e.args else 'x, y, z'}",
                         fix) from None
    except (plyfile.PlyParseError, OSError, ValueError, TypeError, IndexError, MemoryError) as e:
        msg = str(e).strip().splitlines()[0][:120] if str(e).strip() else type(e).__name__
        raise InputError(path, f"is not a readable PLY file ({msg})", fix) from None
    bad = ~(np.abs(xyz) <= FLOAT32_SAFE).all(1)  # NaN compares False
    if bad.any():
        raise InputError(path, f"{int(bad.sum())} points have non-finite or out-of-range positions "
                         f"(at most {FLOAT32_SAFE:g} in magnitude)", "filter the point cloud")
    return xyz.reshape(-1, 3), rgb.reshape(-1, 3)
