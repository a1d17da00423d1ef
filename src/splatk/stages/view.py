"""A run's model ready to draw from any camera, for the interactive viewer (`splatk view`).

Frames come from the same model, backend object and background as `splatk eval` uses, so every
kernel looks in the viewer as it is measured. `FramePlanner` decides when a browser's view needs
a new frame and at what resolution, so the view stays interactive on a slow renderer.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from .. import backends
from ..data.types import Camera
from ..device import resolve_device
from ..errors import InputError
from ..models.io import load_model
from ..render_path import look_at_centre
from .render_video import run_background, run_scene


class RunView:
    """RUN's model, its backend resolved once, its cameras by name (test views first), and where
    a viewer starts: the first train camera (name order), or the camera named ``start``."""

    def __init__(self, run: str | Path, backend: str = "auto", device: str = "cpu",
                 scene_path: str | Path | None = None, start: str | None = None):
        model, meta = load_model(Path(run) / "model.pt")
        self.device = resolve_device(device, backend)
        self.renderer = backends.get(backend, self.device)
        self.model = model.to(self.device)
        self.background = torch.tensor(run_background(meta, scene_path), dtype=torch.float32, device=self.device)
        scene = run_scene(meta, scene_path)
        self.cameras = camera_labels(scene.test, scene.train)
        train = sorted(scene.train, key=lambda c: c.name)
        self.centre = look_at_centre(train) if len(train) > 1 else train[0].center.double()
        if start is not None and start not in self.cameras:
            names = ", ".join(list(self.cameras)[:4])
            raise InputError(run, f"the run's scene has no camera named {start!r}",
                             f"give one of its train or test camera names, e.g. {names}")
        self.start = self.cameras[start] if start is not None else train[0]

    def start_pose(self) -> dict:
        """The pose (see `pose`) of the starting camera."""
        return self.pose(self.start)

    def pose(self, camera: Camera) -> dict:
        """``position``, ``look_at``, ``up`` ([3] numpy, world) and ``fov_y`` (radians) that put a
        viewer exactly at ``camera``: ``look_at`` lies on its optical axis at the depth of the
        train cameras' look-at centre, so orbiting turns about the scene."""
        R_c2w = camera.world_to_cam[:3, :3].double().T
        position = camera.center.double()
        forward = R_c2w[:, 2]
        depth = max(float((self.centre - position) @ forward), 1e-3 * (float(position.norm()) or 1.0))
        return {"position": position.numpy(), "look_at": (position + depth * forward).numpy(),
                "up": (-R_c2w[:, 1]).numpy(), "fov_y": 2 * math.atan(camera.height / (2 * camera.fy))}

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


def camera_labels(test: list[Camera], train: list[Camera]) -> dict[str, Camera]:
    """The scene's cameras by the name a viewer lists them under: the camera's own name, prefixed
    with ``test: `` or ``train: `` where the same name is in both splits (NeRF-synthetic's ``r_0``)."""
    shared = {c.name for c in test} & {c.name for c in train}
    labels = {}
    for split, cams in (("test", test), ("train", train)):
        for cam in sorted(cams, key=lambda c: c.name):
            labels[f"{split}: {cam.name}" if cam.name in shared else cam.name] = cam
    return labels


def frame_size(width: int, height: int, longest: int) -> tuple[int, int]:
    """``width`` x ``height`` scaled down (never up) to at most ``longest`` pixels on its longest
    side, at least 2 x 2."""
    scale = min(1.0, longest / max(width, height))
    return max(2, round(width * scale)), max(2, round(height * scale))


class FramePlanner:
    """When one viewer needs a new frame and how large to draw it.

    While the camera moves, every new camera gets a frame whose size is chosen so it takes about
    ``target_s`` to draw (drawing time grows with the pixel count, so the longest side scales with
    the square root of the time ratio); once the camera has rested ``rest_s``, one frame at
    ``max_size`` sharpens the view.

    Args:
        max_size: longest side of a frame at rest, in pixels.
        target_s: seconds one frame may take while the camera moves.
        min_size: the smallest longest side a moving frame shrinks to.
        rest_s: seconds without a camera change before the full-size frame.
    """

    def __init__(self, max_size: int, target_s: float, min_size: int = 64, rest_s: float = 0.25):
        self.max_size, self.target_s, self.rest_s = max_size, target_s, rest_s
        self.min_size = min(min_size, max_size)
        self.moving_size = float(max_size)  # optimistic until a frame has been timed
        self.stamp = None
        self.moved_at = 0.0
        self.sharp = True  # the frame on screen is the full-size one for the current camera

    def next_size(self, stamp: float, now: float) -> int | None:
        """Longest side of the frame to draw now for a camera last changed at ``stamp`` (any value
        that changes with the camera), or None while the frame on screen is current."""
        if stamp != self.stamp:
            self.stamp, self.moved_at = stamp, now
            size = round(self.moving_size)
            self.sharp = size >= self.max_size
            return size
        if not self.sharp and now - self.moved_at >= self.rest_s:
            self.sharp = True
            return self.max_size
        return None

    def drawn(self, size: int, seconds: float, full: bool = False) -> None:
        """Learn from a frame of longest side ``size`` that took ``seconds`` to draw; ``full``: it
        was already as large as a frame at rest would be (a small window), so none follows."""
        self.sharp = self.sharp or full
        if seconds <= 0:
            return
        ideal = size * math.sqrt(self.target_s / seconds)
        # the geometric mean of the old and the ideal size damps the jitter of single frames
        self.moving_size = min(max(math.sqrt(self.moving_size * ideal), self.min_size), self.max_size)
