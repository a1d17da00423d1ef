"""Pieces both loaders share: image checks and decoding, downscaling, poses, splits.

Intrinsics and undistortion live in :mod:`splatk.data.cameras`.
"""
from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence, TypeVar

import cv2
import numpy as np
import torch

from ..errors import InputError
from .borders import EdgeMeans, edge_means, mask_black_bands
from .cameras import FLOAT32_SAFE, Intrinsics, Undistorter, scaled
from .types import Camera

T = TypeVar("T")

#: image suffixes tried when a file name has none (NeRF-synthetic ``./train/r_0``)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG", ".exr", ".webp")

#: peak bytes per pixel while :func:`read_image` decodes one image (the decoded 4-channel image,
#: its float32 copy and the float32 RGB / compositing temporaries), rounded up
DECODE_BYTES_PER_PIXEL = 64

#: OpenCV refuses to decode more pixels than this (its CV_IO_MAX_IMAGE_PIXELS default)
OPENCV_MAX_PIXELS = 1 << 30


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


def _is_file(path: Path) -> bool:
    try:
        return path.is_file()
    except (OSError, ValueError):  # a name too long for the file system, an embedded NUL
        return False


def resolve_image(path: Path) -> Path | None:
    """``path`` if it exists, else ``path`` + a known image suffix (when it has none)."""
    if _is_file(path):
        return path
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        for suf in IMAGE_SUFFIXES:
            cand = path.with_name(path.name + suf)
            if _is_file(cand):
                return cand
    return None


def has_control_characters(name: str) -> bool:
    """Whether ``name`` holds a line break, tab or other control character (which would split or
    garble the one-line error that names the file)."""
    return any(ord(ch) < 0x20 or 0x7F <= ord(ch) < 0xA0 for ch in name)


def is_inside(path: Path, folder: Path) -> bool:
    """Whether ``path`` lies under ``folder`` once ``.`` and ``..`` are collapsed.

    Symbolic links are not followed: a link placed inside the scene folder (e.g. ``images`` ->
    a photo archive) is the user's choice, while a ``..`` or absolute path written in a data file
    must not reach outside the folder the user pointed splatk at.
    """
    p = os.path.normpath(os.path.abspath(path))
    f = os.path.normpath(os.path.abspath(folder))
    try:
        return os.path.commonpath([p, f]) == f
    except ValueError:  # different drives
        return False


def physical_memory_bytes() -> int:
    """This machine's physical memory (8 GiB where the OS does not say)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return 8 << 30


def max_image_pixels() -> int:
    """The most pixels one image may have: decoding it must fit in half of physical memory."""
    return min(physical_memory_bytes() // 2 // DECODE_BYTES_PER_PIXEL, OPENCV_MAX_PIXELS)


def check_image_pixels(path: Path, width: int, height: int) -> None:
    """Refuse (from the header size, before decoding) an image that cannot be decoded here."""
    if width < 1 or height < 1:
        raise InputError(path, f"image header declares an empty {width}x{height} image",
                         "re-copy or replace the file, or remove it from the scene")
    limit = max_image_pixels()
    if width * height > limit:
        need = width * height * DECODE_BYTES_PER_PIXEL
        raise InputError(path, f"image header declares {width}x{height} pixels ({width * height / 1e6:.0f} "
                         f"megapixels, about {need / 2**30:.0f} GiB to decode); this machine "
                         f"({physical_memory_bytes() / 2**30:.0f} GiB of memory) decodes at most "
                         f"{limit / 1e6:.0f} megapixels per image",
                         "downscale the image files (e.g. 4000 pixels wide) or remove the image from the scene")


def check_image_file(path: Path, listed_in: str) -> None:
    """Existence and non-empty checks (cheap; done for every image before decoding any)."""
    if not _is_file(path):
        raise InputError(path, f"image listed in {listed_in} does not exist",
                         f"add the image or remove its entry from {listed_in}")
    if path.stat().st_size == 0:
        raise InputError(path, "image file is empty (0 bytes)",
                         f"re-copy the image or remove its entry from {listed_in}")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header (no decode); raises InputError if unreadable or too
    large to decode on this machine (:func:`check_image_pixels`).

    EXIF orientation is ignored here and when decoding, as COLMAP does.
    """
    from PIL import Image  # pillow comes with matplotlib

    # check_image_pixels applies a cap from this machine's memory; pillow's fixed one would warn
    # about or refuse (with an exception of its own) images that fit
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        saved, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
        try:
            with Image.open(path) as im:
                width, height = int(im.size[0]), int(im.size[1])
        except (OSError, ValueError, SyntaxError, EOFError):  # UnidentifiedImageError is an OSError
            raise InputError(path, "image cannot be decoded (corrupt, truncated or not an image)",
                             "re-copy or replace the file, or remove it from the scene") from None
        finally:
            Image.MAX_IMAGE_PIXELS = saved
    check_image_pixels(path, width, height)
    return width, height


def _decode(path: Path) -> np.ndarray:
    """The pixels of an image file as ``cv2.imdecode(..., IMREAD_UNCHANGED)`` returns them."""
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
    return img


def _to_uint8(x: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.clip(x * 255.0 + 0.5, 0, 255).astype(np.uint8))


def read_image(path: Path, background: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Decode an image to [H, W, 3] uint8 RGB; RGBA is composited onto ``background`` (RGB in [0, 1])."""
    return read_image_and_alpha(path, background)[0]


def read_image_and_alpha(path: Path, background: Sequence[float] = (0.0, 0.0, 0.0)
                         ) -> tuple[np.ndarray, np.ndarray | None]:
    """(:func:`read_image`'s [H, W, 3] uint8 RGB, its alpha channel as [H, W] uint8 or None)."""
    img = _decode(path)
    alpha = None
    if img.ndim == 3 and img.shape[2] in (2, 4):
        scale = 65535.0 if img.dtype == np.uint16 else 255.0 if img.dtype == np.uint8 else 1.0
        alpha = _to_uint8(np.clip(img[:, :, -1].astype(np.float32) / scale, 0.0, 1.0))
    return _to_uint8(to_rgb(img, path, background)), alpha


def read_mask(path: Path) -> np.ndarray:
    """A mask image as [H, W] bool: True (the pixel counts) where it is brighter than 50% grey;
    transparent pixels of an RGBA mask count as black."""
    return to_rgb(_decode(path), path).mean(axis=2) >= 0.5


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


def resize(image: np.ndarray, width: int, height: int, nearest: bool = False) -> np.ndarray:
    if image.shape[1] == width and image.shape[0] == height:
        return image
    interp = (cv2.INTER_NEAREST if nearest else cv2.INTER_AREA if width <= image.shape[1] else cv2.INTER_LINEAR)
    return np.ascontiguousarray(cv2.resize(image, (width, height), interpolation=interp))


@dataclass
class View:
    """One checked view, before decoding: its camera and where its pixels are.

    Attributes:
        name: image name relative to the scene's image folder (as the dataset lists it).
        intr: the camera of the file at ``path`` (an ``images_N`` file's: scaled to its size).
        world_to_cam: [4, 4] rigid transform.
        path: the image file to decode.
        mask_path: a mask image (white: the pixel counts), or None.
    """

    name: str
    intr: Intrinsics
    world_to_cam: np.ndarray
    path: Path
    mask_path: Path | None = None


def make_camera(view: View, undistorter: Undistorter, downscale: float, load_images: bool,
                background: Sequence[float]) -> tuple[Camera, EdgeMeans | None]:
    """Decode (if ``load_images``), undistort, downscale and wrap ``view`` as a pinhole
    :class:`Camera`; its mask and alpha channel go through the same warp. Beside it, the
    undistorted image's edge means before the downscale (None without images), for
    :func:`splatk.data.borders.mask_black_bands`."""
    intr = view.intr
    pin, _ = undistorter.geometry(intr)
    out = scaled(pin, downscale)
    image = alpha = mask = edges = None
    if load_images:
        rgb, a = read_image_and_alpha(view.path, background)
        if rgb.shape[:2] != (intr.height, intr.width):  # header and pixels disagree
            raise InputError(view.path, f"decoded image is {rgb.shape[1]}x{rgb.shape[0]}, expected "
                             f"{intr.width}x{intr.height}", "re-copy the image")
        full = undistorter.apply(rgb, intr)
        edges = edge_means(full) if a is None else None  # an RGBA image's edge is its background
        image = torch.from_numpy(resize(full, out.width, out.height))
        if a is not None:
            alpha = torch.from_numpy(resize(undistorter.apply(a, intr), out.width, out.height))
        if view.mask_path is not None:
            m = read_mask(view.mask_path).astype(np.uint8)
            m = resize(m, intr.width, intr.height, nearest=True)  # a full-size mask of an images_N view
            m = resize(undistorter.apply(m, intr, nearest=True), out.width, out.height, nearest=True)
            mask = torch.from_numpy(m.astype(bool))
    return Camera(name=view.name, width=out.width, height=out.height, fx=out.fx, fy=out.fy, cx=out.cx, cy=out.cy,
                  world_to_cam=torch.from_numpy(np.asarray(view.world_to_cam, dtype=np.float32).copy()),
                  image=image, image_path=view.path, mask=mask, alpha=alpha), edges


def make_cameras(views: list[View], undistorter: Undistorter, downscale: float, load_images: bool,
                 background: Sequence[float], scene_warnings: list[str]) -> list[Camera]:
    """:func:`make_camera` for every view, then each image size's black border left out of the
    masks (:mod:`splatk.data.borders`; a warning says where)."""
    made = [make_camera(view, undistorter, downscale, load_images, background) for view in views]
    cams = [c for c, _ in made]
    mask_black_bands(cams, [e for _, e in made], scene_warnings)
    return cams


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
    if np.abs(R).max() > 2.0:  # far from a rotation (and an SVD of huge values may not converge)
        return None
    U, S, Vt = np.linalg.svd(R)
    if np.abs(S - 1.0).max() > tol or np.linalg.det(R) <= 0:
        return None
    out = np.eye(4)
    out[:3, :3] = U @ Vt
    out[:3, 3] = t
    return out


def check_translation(world_to_cam: np.ndarray, path: Path, where: str) -> None:
    """Camera centre and translation at most :data:`FLOAT32_SAFE` in magnitude (poses become float32)."""
    centre = -world_to_cam[:3, :3].T @ world_to_cam[:3, 3]
    if not (np.abs(world_to_cam[:3, 3]).max() <= FLOAT32_SAFE and np.abs(centre).max() <= FLOAT32_SAFE):
        raise InputError(path, f"{where} has a camera position out of range "
                         f"({', '.join(f'{v:g}' for v in centre)}; at most {FLOAT32_SAFE:g} in magnitude)",
                         "fix the pose (a value too large for float32)")


def split_every(items: list[T], test_every: int | None) -> tuple[list[T], list[T]]:
    """(train, test): item i is a test item when i % test_every == 0 (3DGS / mip-NeRF 360).

    ``test_every`` of 0 or None puts everything in train.
    """
    if not test_every or test_every <= 0:
        return list(items), []
    test = [x for i, x in enumerate(items) if i % test_every == 0]
    train = [x for i, x in enumerate(items) if i % test_every != 0]
    return train, test
