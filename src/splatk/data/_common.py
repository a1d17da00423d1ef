"""Pieces both loaders share: image checks and decoding, undistortion, downscaling, poses, splits.

Pixel convention (as in :class:`~splatk.data.types.Camera` and COLMAP): pixel (i, j) has its centre
at (i + 0.5, j + 0.5). OpenCV puts pixel centres on integers, so principal points are shifted by
0.5 on the way into and out of ``cv2``. With half-pixel centres, resizing by s scales
fx, fy, cx, cy by exactly s.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence, TypeVar

import cv2
import numpy as np
import torch

from ..errors import InputError
from .types import Camera

T = TypeVar("T")

#: image suffixes tried when a file name has none (NeRF-synthetic ``./train/r_0``)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG", ".exr", ".webp")


@dataclass(frozen=True)
class Intrinsics:
    """A (possibly distorted) perspective camera: size, pinhole part and OpenCV distortion.

    ``dist`` is in OpenCV order (k1, k2, p1, p2[, k3[, k4, k5, k6]]); all zeros means pinhole.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = ()

    @property
    def distorted(self) -> bool:
        return any(d != 0.0 for d in self.dist)

    def values(self) -> list[float]:
        return [self.fx, self.fy, self.cx, self.cy, *self.dist]


# ----------------------------------------------------------------------------------------------
# image files


def check_downscale(downscale: float) -> float:
    try:
        f = float(downscale)
    except (TypeError, ValueError):
        f = float("nan")
    if not math.isfinite(f) or f <= 0:
        raise InputError(None, f"downscale must be a positive number, got {downscale!r}",
                         "use e.g. 1, 2 or 4 (images are resized by 1/downscale)")
    return f


def resolve_image(path: Path) -> Path | None:
    """``path`` if it exists, else ``path`` + a known image suffix (when it has none)."""
    if path.is_file():
        return path
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        for suf in IMAGE_SUFFIXES:
            cand = path.with_name(path.name + suf)
            if cand.is_file():
                return cand
    return None


def check_image_file(path: Path, listed_in: str) -> None:
    """Existence and non-empty checks (cheap; done for every image before decoding any)."""
    if not path.is_file():
        raise InputError(path, f"image listed in {listed_in} does not exist",
                         f"add the image or remove its entry from {listed_in}")
    if path.stat().st_size == 0:
        raise InputError(path, "image file is empty (0 bytes)",
                         f"re-copy the image or remove its entry from {listed_in}")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header (no decode); raises InputError if unreadable.

    EXIF orientation is ignored here and when decoding, as COLMAP does.
    """
    try:
        from PIL import Image, UnidentifiedImageError
    except ImportError:  # pragma: no cover - pillow comes with matplotlib
        img = read_image(path)
        return img.shape[1], img.shape[0]
    try:
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise InputError(path, "image cannot be decoded (corrupt, truncated or not an image)",
                         "re-copy or replace the file, or remove it from the scene") from None


def read_image(path: Path, background: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Decode an image to [H, W, 3] uint8 RGB; RGBA is composited onto ``background`` (RGB in [0, 1])."""
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as e:
        raise InputError(path, f"image cannot be read ({e.strerror})", "check the file permissions") from None
    if data.size == 0:
        raise InputError(path, "image file is empty (0 bytes)", "re-copy the image or remove it from the scene")
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise InputError(path, "image cannot be decoded (corrupt or not an image)",
                         "re-copy or replace the file, or remove it from the scene")
    rgb = to_rgb(img, path, background)
    return np.ascontiguousarray(np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8))


def to_rgb(img: np.ndarray, path: Path, background: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Pixels as ``cv2.imdecode(..., IMREAD_UNCHANGED)`` returns them (grey, grey + alpha, BGR or
    BGRA; 8-bit, 16-bit or float) as [H, W, 3] float32 RGB in [0, 1], an alpha channel composited
    onto ``background`` (RGB in [0, 1]): how every image splatk measures is read (scene loading,
    ``splatk compare``). ``path`` names the file in errors."""
    if img.dtype == np.uint16:
        img = img.astype(np.float32) / 65535.0
    elif img.dtype == np.uint8:
        img = img.astype(np.float32) / 255.0
    elif img.dtype in (np.float32, np.float64):  # EXR etc.: assume linear [0, 1]
        img = np.clip(img.astype(np.float32), 0.0, 1.0)
    else:
        raise InputError(path, f"unsupported pixel type {img.dtype}", "convert the image to 8-bit PNG or JPEG")
    if img.ndim == 2:
        img = img[:, :, None]
    ch = img.shape[2]
    if ch == 1:
        rgb, alpha = np.repeat(img, 3, axis=2), None
    elif ch == 2:  # grey + alpha
        rgb, alpha = np.repeat(img[:, :, :1], 3, axis=2), img[:, :, 1:2]
    elif ch == 3:
        rgb, alpha = img[:, :, ::-1], None
    elif ch == 4:
        rgb, alpha = img[:, :, 2::-1], img[:, :, 3:4]
    else:
        raise InputError(path, f"image has {ch} channels", "use an RGB or RGBA image")
    if alpha is not None:
        bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
        rgb = rgb * alpha + bg * (1.0 - alpha)
    return np.ascontiguousarray(rgb, dtype=np.float32)


# ----------------------------------------------------------------------------------------------
# undistortion and downscaling


class Undistorter:
    """Maps distorted cameras to undistorted pinhole ones; caches per distinct camera.

    ``cv2.getOptimalNewCameraMatrix`` with alpha = 0 (only valid pixels), then
    ``initUndistortRectifyMap`` + ``remap`` and a crop to the valid ROI (cx, cy shift by the crop).
    """

    def __init__(self) -> None:
        self._geo: dict[Intrinsics, tuple[Intrinsics, tuple[int, int, int, int]]] = {}
        self._maps: dict[Intrinsics, tuple[np.ndarray, np.ndarray]] = {}

    @staticmethod
    def _cv_K(intr: Intrinsics) -> np.ndarray:
        # OpenCV pixel centres are integers: shift the half-pixel-convention principal point
        return np.array([[intr.fx, 0.0, intr.cx - 0.5], [0.0, intr.fy, intr.cy - 0.5], [0.0, 0.0, 1.0]])

    def geometry(self, intr: Intrinsics) -> tuple[Intrinsics, tuple[int, int, int, int]]:
        """Undistorted pinhole intrinsics (after the crop) and the crop ROI (x, y, w, h)."""
        if not intr.distorted:
            return intr, (0, 0, intr.width, intr.height)
        if intr not in self._geo:
            size = (intr.width, intr.height)
            newK, roi = cv2.getOptimalNewCameraMatrix(self._cv_K(intr), np.asarray(intr.dist, np.float64),
                                                      size, 0, size)
            x, y, w, h = (int(v) for v in roi)
            if w <= 0 or h <= 0:  # degenerate distortion: keep the full frame
                x, y, w, h = 0, 0, intr.width, intr.height
            out = Intrinsics(w, h, float(newK[0, 0]), float(newK[1, 1]),
                             float(newK[0, 2]) + 0.5 - x, float(newK[1, 2]) + 0.5 - y)
            self._geo[intr] = (out, (x, y, w, h))
        return self._geo[intr]

    def apply(self, image: np.ndarray, intr: Intrinsics) -> np.ndarray:
        if not intr.distorted:
            return image
        out, (x, y, w, h) = self.geometry(intr)
        if intr not in self._maps:
            size = (intr.width, intr.height)
            newK = np.array([[out.fx, 0.0, out.cx - 0.5 + x], [0.0, out.fy, out.cy - 0.5 + y], [0.0, 0.0, 1.0]])
            self._maps[intr] = cv2.initUndistortRectifyMap(
                self._cv_K(intr), np.asarray(intr.dist, np.float64), None, newK, size, cv2.CV_32FC1)
        m1, m2 = self._maps[intr]
        und = cv2.remap(image, m1, m2, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return np.ascontiguousarray(und[y:y + h, x:x + w])


def scaled(intr: Intrinsics, downscale: float) -> Intrinsics:
    """Intrinsics of the image resized by 1 / downscale (sizes rounded half up)."""
    if downscale == 1.0:
        return intr
    w = max(1, int(intr.width / downscale + 0.5))
    h = max(1, int(intr.height / downscale + 0.5))
    sx, sy = w / intr.width, h / intr.height
    return Intrinsics(w, h, intr.fx * sx, intr.fy * sy, intr.cx * sx, intr.cy * sy, intr.dist)


def resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    if image.shape[1] == width and image.shape[0] == height:
        return image
    interp = cv2.INTER_AREA if width <= image.shape[1] else cv2.INTER_LINEAR
    return np.ascontiguousarray(cv2.resize(image, (width, height), interpolation=interp))


def make_camera(name: str, intr: Intrinsics, world_to_cam: np.ndarray, undistorter: Undistorter,
                downscale: float, image: np.ndarray | None, image_path: Path | None) -> Camera:
    """Undistort (if needed), downscale and wrap as a pinhole :class:`Camera`."""
    pin, _ = undistorter.geometry(intr)
    out = scaled(pin, downscale)
    img_t = None
    if image is not None:
        image = resize(undistorter.apply(image, intr), out.width, out.height)
        img_t = torch.from_numpy(image)
    return Camera(name=name, width=out.width, height=out.height, fx=out.fx, fy=out.fy, cx=out.cx, cy=out.cy,
                  world_to_cam=torch.from_numpy(np.asarray(world_to_cam, dtype=np.float32).copy()),
                  image=img_t, image_path=image_path)


# ----------------------------------------------------------------------------------------------
# poses and splits


def rigid_or_none(M: np.ndarray, tol: float = 0.05) -> np.ndarray | None:
    """Clean up a [4, 4] (or [3, 4]) rigid transform: re-orthonormalise a nearly orthonormal rotation.

    Returns None if the matrix is not finite or not close to a rotation (det +1).
    """
    M = np.asarray(M, dtype=np.float64)
    if M.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(M)):
        return None
    R, t = M[:3, :3], M[:3, 3]
    U, S, Vt = np.linalg.svd(R)
    if np.abs(S - 1.0).max() > tol or np.linalg.det(R) <= 0:
        return None
    out = np.eye(4)
    out[:3, :3] = U @ Vt
    out[:3, 3] = t
    return out


def split_every(items: list[T], test_every: int | None) -> tuple[list[T], list[T]]:
    """(train, test): item i is a test item when i % test_every == 0 (3DGS / mip-NeRF 360).

    ``test_every`` of 0 or None puts everything in train.
    """
    if not test_every or test_every <= 0:
        return list(items), []
    test = [x for i, x in enumerate(items) if i % test_every == 0]
    train = [x for i, x in enumerate(items) if i % test_every != 0]
    return train, test
