"""Files of plain 3DGS Gaussians that other tools open: the 3DGS PLY, antimatter15's ``.splat``
and Niantic's SPZ. Each writer takes :class:`Gaussians` (``gaussians``), the model as a 3DGS
viewer sees it; the stage (``splatk.stages.export``) builds them and reports what was lost."""
from __future__ import annotations

from .gaussians import Gaussians, gaussians_of
from .ply import ply_arrays, write_ply
from .splat import write_splat
from .spz import check_spz_range, write_spz

__all__ = ["Gaussians", "gaussians_of", "ply_arrays", "write_ply", "write_splat", "write_spz", "check_spz_range"]
