"""Initial primitive positions and colours: SfM points or uniform random points."""
from __future__ import annotations

import torch

from ..data.types import Scene
from ..errors import InputError


def initial_points(scene: Scene, init: str, budget: int, random_points: int = 100_000,
                   seed: int = 0, random_extent: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Points [P, 3] and colours [P, 3] to start from, never more than ``budget``.

    ``sfm``: the scene's SfM points (randomly subsampled to the budget: a model should not
    start larger than it may grow). ``random``: uniform in a cube of half-width
    ``random_extent`` x the scene extent around the point the cameras look at (3DGS-MCMC uses
    3x the extent around the origin: most of those points start outside every view or right
    in front of a camera, where they occlude it for thousands of iterations).
    """
    g = torch.Generator().manual_seed(seed)
    if init == "sfm":
        if scene.points.shape[0] == 0:
            raise InputError(scene.root, "the scene has no SfM points to initialise from",
                             "use --init random")
        pts, cols = scene.points.float(), scene.point_colors.float()
        if pts.shape[0] > budget:
            keep = torch.randperm(pts.shape[0], generator=g)[:budget]
            pts, cols = pts[keep], cols[keep]
        return pts, cols
    if init == "random":
        n = min(budget, random_points)
        centre = _look_at_centre(scene)
        pts = centre + (torch.rand(n, 3, generator=g) * 2 - 1) * scene.extent * random_extent
        cols = torch.rand(n, 3, generator=g)
        return pts, cols
    raise ValueError(f"unknown init {init!r}; use sfm or random")


def _look_at_centre(scene: Scene) -> torch.Tensor:
    """Least-squares point closest to all train cameras' optical axes (object-centric
    captures look at it); falls back to the mean camera centre."""
    A = torch.zeros(3, 3, dtype=torch.float64)
    b = torch.zeros(3, dtype=torch.float64)
    for cam in scene.train:
        c = cam.center.double()
        d = cam.world_to_cam[2, :3].double()  # optical axis in world coordinates
        d = d / d.norm()
        P = torch.eye(3, dtype=torch.float64) - d[:, None] * d[None, :]
        A += P
        b += P @ c
    try:
        x = torch.linalg.solve(A, b)
        if torch.isfinite(x).all():
            return x.float()
    except RuntimeError:
        pass
    return torch.stack([c.center for c in scene.train]).mean(0)
