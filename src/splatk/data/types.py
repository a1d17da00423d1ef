"""Cameras and scenes as the engine sees them, independent of the file format they came from."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch


@dataclass
class Camera:
    """One posed, undistorted pinhole view.

    Conventions: OpenCV camera axes (x right, y down, z forward); pixel (i, j) has its centre at
    (i + 0.5, j + 0.5), so cx = width / 2 is the image centre.

    Attributes:
        name: image file name (relative to the scene's image folder).
        width, height: image size in pixels after downscaling / undistortion.
        fx, fy, cx, cy: pinhole intrinsics in pixels.
        world_to_cam: [4, 4] float32 rigid transform (world -> camera).
        image: [H, W, 3] uint8 RGB, already undistorted, downscaled and composited on the
            background (None if images were not loaded).
        image_path: where the image came from (for messages).
        mask: [H, W] bool, True where the pixel counts (the dataset's mask, warped as the image);
            None: every pixel counts. Masked pixels leave the training loss and the metrics.
        alpha: [H, W] uint8 alpha channel of an RGBA image (``image`` is already composited on
            the scene's background), or None; ``--background random`` recomposites with it.
    """

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_to_cam: torch.Tensor
    image: torch.Tensor | None = None
    image_path: Path | None = None
    mask: torch.Tensor | None = None
    alpha: torch.Tensor | None = None

    @property
    def K(self) -> torch.Tensor:
        """[3, 3] intrinsics matrix."""
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=torch.float32
        )

    @property
    def center(self) -> torch.Tensor:
        """[3] camera centre in world coordinates."""
        R = self.world_to_cam[:3, :3]
        t = self.world_to_cam[:3, 3]
        return -R.T @ t

    def image_float(self, device: torch.device | str = "cpu") -> torch.Tensor:
        """[H, W, 3] float32 in [0, 1]."""
        assert self.image is not None, f"image of {self.name} not loaded"
        return self.image.to(device=device, dtype=torch.float32) / 255.0

    def mask_float(self, device: torch.device | str = "cpu") -> torch.Tensor | None:
        """[H, W, 1] float32, 1 where the pixel counts, 0 where masked; None without a mask."""
        return None if self.mask is None else self.mask.to(device=device, dtype=torch.float32)[..., None]

    def alpha_float(self, device: torch.device | str = "cpu") -> torch.Tensor | None:
        """[H, W, 1] float32 alpha in [0, 1]; None for an image without an alpha channel."""
        return None if self.alpha is None else self.alpha.to(device=device, dtype=torch.float32)[..., None] / 255.0


@dataclass
class Scene:
    """A multi-view scene: train/test cameras and an optional SfM point cloud.

    Attributes:
        root: the scene folder.
        train, test: cameras; test is the dataset's own test list, else every 8th image.
        points: [P, 3] float32 SfM points (may be empty, P = 0).
        point_colors: [P, 3] float32 in [0, 1].
        background: RGB in [0, 1] that RGBA images were composited on (and renders use).
        source: short description of the loader ("colmap", "transforms").
        warnings: what the loader read past without using (e.g. dataset fields splatk does not
            use), one line each, for the caller to print.
        test_listed: the dataset names its own test views (``transforms_test.json``), so
            ``test_every`` had no say in the split.
    """

    root: Path
    train: list[Camera]
    test: list[Camera]
    points: torch.Tensor = field(default_factory=lambda: torch.zeros(0, 3))
    point_colors: torch.Tensor = field(default_factory=lambda: torch.zeros(0, 3))
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    source: str = ""
    warnings: list[str] = field(default_factory=list)
    test_listed: bool = False

    @property
    def cameras(self) -> list[Camera]:
        return self.train + self.test

    @property
    def extent(self) -> float:
        """Scene radius as 3DGS defines it: 1.1 x the largest distance of a train camera
        centre from the mean centre (used to scale position learning rates and random init)."""
        centers = torch.stack([c.center for c in self.train])
        d = (centers - centers.mean(0)).norm(dim=1).max().item()
        return 1.1 * max(d, 1e-6)
