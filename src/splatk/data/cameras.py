"""Camera intrinsics as datasets write them, and their undistortion to a pinhole camera.

Two lens families: OpenCV's perspective model (radial-tangential, optionally rational) and
OpenCV's fisheye model (equidistant, ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6
+ k4 theta^8)``), which is also COLMAP's ``OPENCV_FISHEYE`` and, with fewer coefficients,
``RADIAL_FISHEYE``, ``SIMPLE_RADIAL_FISHEYE``, ``FISHEYE`` and ``SIMPLE_FISHEYE``.

Pixel convention (as in :class:`~splatk.data.types.Camera` and COLMAP): pixel (i, j) has its centre
at (i + 0.5, j + 0.5). OpenCV puts pixel centres on integers, so principal points are shifted by
0.5 on the way into and out of ``cv2``. With half-pixel centres, resizing by s scales
fx, fy, cx, cy by exactly s.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError

#: largest magnitude accepted for a coordinate, focal length or principal point: its square must
#: stay finite in float32 (max 3.4e38), since the renderer squares distances
FLOAT32_SAFE = 1e18


@dataclass(frozen=True)
class Intrinsics:
    """A (possibly distorted) camera: size, pinhole part and distortion.

    ``dist`` is in OpenCV order: for a perspective lens (k1, k2, p1, p2[, k3[, k4, k5, k6]]), all
    zeros meaning pinhole; for a fisheye lens (``fisheye=True``) the four coefficients
    (k1, k2, k3, k4) of ``cv2.fisheye``. A fisheye lens is never a pinhole, even with k = 0.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = ()
    fisheye: bool = False

    @property
    def distorted(self) -> bool:
        return self.fisheye or any(d != 0.0 for d in self.dist)

    def values(self) -> list[float]:
        return [self.fx, self.fy, self.cx, self.cy, *self.dist]


def fisheye_intrinsics(width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                       k: tuple[float, ...] = ()) -> Intrinsics:
    """An OpenCV fisheye camera; ``k`` holds up to four coefficients (missing ones are 0)."""
    k = tuple(float(v) for v in k) + (0.0,) * (4 - len(k))
    return Intrinsics(width, height, fx, fy, cx, cy, k[:4], fisheye=True)


class Undistorter:
    """Maps distorted cameras to undistorted pinhole ones; caches per distinct camera.

    Perspective lenses: ``cv2.getOptimalNewCameraMatrix`` with alpha = 0 (only valid pixels),
    then ``initUndistortRectifyMap`` + ``remap`` and a crop to the valid ROI (cx, cy shift by
    the crop). Fisheye lenses: ``cv2.fisheye.estimateNewCameraMatrixForUndistortRectify`` with
    balance = 0 (the focal length that leaves no pixel without a source, as nerfstudio
    undistorts) at the same image size, then ``cv2.fisheye.initUndistortRectifyMap`` + ``remap``.
    """

    def __init__(self) -> None:
        self._geo: dict[Intrinsics, tuple[Intrinsics, tuple[int, int, int, int]]] = {}
        self._maps: dict[Intrinsics, tuple[np.ndarray, np.ndarray]] = {}

    @staticmethod
    def _cv_K(intr: Intrinsics) -> np.ndarray:
        # OpenCV pixel centres are integers: shift the half-pixel-convention principal point
        return np.array([[intr.fx, 0.0, intr.cx - 0.5], [0.0, intr.fy, intr.cy - 0.5], [0.0, 0.0, 1.0]])

    @staticmethod
    def _cv_dist(intr: Intrinsics) -> np.ndarray:
        return np.asarray(intr.dist, np.float64).reshape(4, 1) if intr.fisheye else np.asarray(intr.dist, np.float64)

    def geometry(self, intr: Intrinsics) -> tuple[Intrinsics, tuple[int, int, int, int]]:
        """Undistorted pinhole intrinsics (after the crop) and the crop ROI (x, y, w, h)."""
        if not intr.distorted:
            return intr, (0, 0, intr.width, intr.height)
        if intr not in self._geo:
            size = (intr.width, intr.height)
            if intr.fisheye:
                newK = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
                    self._cv_K(intr), self._cv_dist(intr), size, np.eye(3), balance=0.0)
                x, y, w, h = 0, 0, intr.width, intr.height
            else:
                newK, roi = cv2.getOptimalNewCameraMatrix(self._cv_K(intr), self._cv_dist(intr), size, 0, size)
                x, y, w, h = (int(v) for v in roi)
                if w <= 0 or h <= 0:  # degenerate distortion: keep the full frame
                    x, y, w, h = 0, 0, intr.width, intr.height
            out = Intrinsics(w, h, float(newK[0, 0]), float(newK[1, 1]),
                             float(newK[0, 2]) + 0.5 - x, float(newK[1, 2]) + 0.5 - y)
            self._geo[intr] = (out, (x, y, w, h))
        return self._geo[intr]

    def apply(self, image: np.ndarray, intr: Intrinsics, nearest: bool = False) -> np.ndarray:
        """``image`` [H, W] or [H, W, C] as the undistorted camera sees it; ``nearest``
        interpolation for labels (masks)."""
        if not intr.distorted:
            return image
        out, (x, y, w, h) = self.geometry(intr)
        if intr not in self._maps:
            size = (intr.width, intr.height)
            newK = np.array([[out.fx, 0.0, out.cx - 0.5 + x], [0.0, out.fy, out.cy - 0.5 + y], [0.0, 0.0, 1.0]])
            if intr.fisheye:
                self._maps[intr] = cv2.fisheye.initUndistortRectifyMap(
                    self._cv_K(intr), self._cv_dist(intr), np.eye(3), newK, size, cv2.CV_32FC1)
            else:
                self._maps[intr] = cv2.initUndistortRectifyMap(
                    self._cv_K(intr), self._cv_dist(intr), None, newK, size, cv2.CV_32FC1)
        m1, m2 = self._maps[intr]
        interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        und = cv2.remap(image, m1, m2, interpolation=interp, borderMode=cv2.BORDER_REPLICATE)
        return np.ascontiguousarray(und[y:y + h, x:x + w])


def check_intrinsics(intr: Intrinsics, path: Path, where: str) -> None:
    """Focal lengths positive, principal point at most one image size outside the image, every
    value finite and at most :data:`FLOAT32_SAFE`; ``where`` names the camera in ``path``."""
    values = intr.values()
    if not all(math.isfinite(v) and abs(v) <= FLOAT32_SAFE for v in values):
        raise InputError(path, f"{where} has a non-finite or out-of-range intrinsic value "
                         f"({', '.join(f'{v:g}' for v in values)}; at most {FLOAT32_SAFE:g} in magnitude)",
                         "fix the camera's intrinsics")
    if not (intr.fx > 0 and intr.fy > 0):
        raise InputError(path, f"{where} has focal length fx={intr.fx:g}, fy={intr.fy:g}; both must be positive",
                         "focal lengths are in pixels, about the image width for a normal lens")
    if not (-intr.width <= intr.cx <= 2 * intr.width and -intr.height <= intr.cy <= 2 * intr.height):
        raise InputError(path, f"{where} has its principal point ({intr.cx:g}, {intr.cy:g}) more than an image "
                         f"size outside its {intr.width}x{intr.height} image",
                         "cx, cy are in pixels, usually near the image centre")


def pinhole(intr: Intrinsics, undistorter: Undistorter, path: Path, where: str) -> Intrinsics:
    """The undistorted pinhole camera of ``intr`` (checked), or InputError when its distortion
    leaves no usable image."""
    check_intrinsics(intr, path, where)
    try:
        out, _ = undistorter.geometry(intr)
    except cv2.error:
        out = None
    if out is None or not (out.fx > 0 and out.fy > 0 and all(math.isfinite(v) and abs(v) <= FLOAT32_SAFE
                                                             for v in out.values())):
        order = "fisheye k1, k2, k3, k4" if intr.fisheye else "OpenCV order k1, k2, p1, p2, k3"
        raise InputError(path, f"{where}: its distortion coefficients ({', '.join(f'{d:g}' for d in intr.dist)}) "
                         "leave no usable undistorted image",
                         f"check the distortion values ({order}) or undistort the images first")
    return out


def scaled(intr: Intrinsics, downscale: float) -> Intrinsics:
    """Intrinsics of the image resized by 1 / downscale (sizes rounded half up)."""
    if downscale == 1.0:
        return intr
    w = max(1, int(intr.width / downscale + 0.5))
    h = max(1, int(intr.height / downscale + 0.5))
    return at_size(intr, w, h)


def at_size(intr: Intrinsics, width: int, height: int) -> Intrinsics:
    """Intrinsics of the same view resized to ``width`` x ``height`` (each axis by its own ratio;
    distortion coefficients act on normalised coordinates and stay)."""
    if (width, height) == (intr.width, intr.height):
        return intr
    sx, sy = width / intr.width, height / intr.height
    return replace(intr, width=width, height=height, fx=intr.fx * sx, fy=intr.fy * sy, cx=intr.cx * sx,
                   cy=intr.cy * sy)
