"""A run's model ready to draw from any camera, for the interactive viewer (`splatk view`).

Frames come from the same model, backend object and background as `splatk eval` uses, so every
kernel looks in the viewer as it is measured.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from .. import backends
from ..data.types import Camera
from ..device import resolve_device
from ..models.io import load_model
from ..render_path import look_at_centre
from .render_video import run_background, run_scene


class RunView:
    """RUN's model, its backend resolved once, and where a viewer starts: the first train
    camera (name order) looking at the train cameras' look-at centre."""

    def __init__(self, run: str | Path, backend: str = "auto", device: str = "cpu",
                 scene_path: str | Path | None = None):
        model, meta = load_model(Path(run) / "model.pt")
        self.device = resolve_device(device, backend)
        self.renderer = backends.get(backend, self.device)
        self.model = model.to(self.device)
        self.background = torch.tensor(run_background(meta, scene_path), dtype=torch.float32, device=self.device)
        train = sorted(run_scene(meta, scene_path).train, key=lambda c: c.name)
        self.start = train[0]
        self.centre = look_at_centre(train) if len(train) > 1 else train[0].center.double()

    def start_pose(self) -> dict:
        """``position``, ``look_at``, ``up`` ([3] numpy, world) and ``fov_y`` (radians) of the
        starting camera."""
        R_c2w = self.start.world_to_cam[:3, :3].double().T
        return {"position": self.start.center.double().numpy(), "look_at": self.centre.numpy(),
                "up": (-R_c2w[:, 1]).numpy(), "fov_y": 2 * math.atan(self.start.height / (2 * self.start.fy))}

    @staticmethod
    def camera(R_c2w: np.ndarray, position: np.ndarray, fov_y: float, width: int, height: int) -> Camera:
        """A pinhole camera (OpenCV axes, square pixels, centred principal point) at ``position``
        with camera-to-world rotation ``R_c2w`` [3, 3] and vertical field of view ``fov_y``."""
        R = torch.as_tensor(np.asarray(R_c2w), dtype=torch.float64)
        t = torch.as_tensor(np.asarray(position), dtype=torch.float64)
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3] = R.T
        w2c[:3, 3] = -R.T @ t
        f = height / (2 * math.tan(fov_y / 2))
        return Camera("view", width, height, f, f, width / 2, height / 2, w2c.float())

    def render(self, camera: Camera) -> np.ndarray:
        """[H, W, 3] uint8 image of ``camera``, as `eval` renders a view."""
        with torch.no_grad():
            img = self.model.render(camera, self.background, backend=self.renderer).image.clamp(0, 1)
        return (img.cpu().numpy() * 255 + 0.5).astype(np.uint8)
