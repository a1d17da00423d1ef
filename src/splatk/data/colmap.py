"""COLMAP scenes: ``root/sparse/0`` (or ``root/sparse``) read with pycolmap, images in ``root/images``
(or ``root/images_N`` for ``--downscale N``: :mod:`splatk.data.downscaled`).

Every camera comes out as an undistorted pinhole (see :mod:`splatk.data.cameras`). The model
files are checked structurally before pycolmap sees them, so a truncated or corrupt
``cameras.bin`` / ``images.bin`` / ``points3D.bin`` gives an :class:`InputError` naming the file
instead of pycolmap's ``IndexError: Rig with ID ... does not exist`` or ``std::bad_alloc``.
"""
from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pycolmap
import torch

from ..errors import InputError
from ._common import (View, check_downscale, check_image_file, check_translation, has_control_characters, image_size,
                      is_inside, make_cameras, rigid_or_none, split_every)
from .cameras import FLOAT32_SAFE, Intrinsics, Undistorter, fisheye_intrinsics, pinhole
from .downscaled import use_downscaled
from .types import Scene

#: COLMAP camera models splatk undistorts (params order as in COLMAP's models.h); the fisheye
#: ones are all OpenCV's equidistant fisheye with fewer or more coefficients
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV",
                    "SIMPLE_FISHEYE", "FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE")
_MODEL_FILES = ("cameras", "images", "points3D")


def _model_num_params() -> dict[int, tuple[str, int]]:
    """COLMAP model id -> (name, number of params), from pycolmap itself."""
    table = {}
    for name, mid in pycolmap.CameraModelId.__members__.items():
        if name == "INVALID":
            continue
        try:
            cam = pycolmap.Camera.create_from_model_id(1, mid, 1.0, 2, 2)
            table[int(mid)] = (name, len(cam.params))
        except Exception:  # pragma: no cover - a model pycolmap cannot instantiate
            pass
    return table


def _unsupported(path: Path, name: str, where: str) -> InputError:
    return InputError(path, f"{where} uses camera model {name}, which splatk does not support",
                      f"supported: {', '.join(SUPPORTED_MODELS)}; undistort the images first "
                      "(colmap image_undistorter) or re-run SfM with one of these models")


def find_model_dir(root: Path) -> Path | None:
    """``root/sparse/0`` or ``root/sparse`` holding cameras.bin / cameras.txt, else None."""
    for d in (root / "sparse" / "0", root / "sparse"):
        if (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file():
            return d
    return None


# ----------------------------------------------------------------------------------------------
# structural checks of the model files (cheap, before pycolmap parses them)


class _Reader:
    def __init__(self, path: Path):
        self.path = path
        self.buf = path.read_bytes()
        self.pos = 0

    def truncated(self, what: str) -> InputError:
        return InputError(self.path, f"is truncated or corrupt ({what} at byte {self.pos} of {len(self.buf)})",
                          "re-copy the file or re-export the COLMAP model")

    def take(self, fmt: str, what: str) -> tuple:
        n = struct.calcsize(fmt)
        if self.pos + n > len(self.buf):
            raise self.truncated(f"file ends inside {what}")
        vals = struct.unpack_from(fmt, self.buf, self.pos)
        self.pos += n
        return vals

    def skip(self, n: int, what: str) -> None:
        if n < 0 or self.pos + n > len(self.buf):
            raise self.truncated(f"file ends inside {what}")
        self.pos += n

    def count(self, min_record: int, what: str) -> int:
        (n,) = self.take("<Q", f"the number of {what}")
        if n * min_record > len(self.buf) - self.pos:
            raise self.truncated(f"its header counts {n} {what}, more than the {len(self.buf)}-byte file holds")
        return n

    def done(self) -> None:
        if self.pos != len(self.buf):
            raise InputError(self.path, f"has {len(self.buf) - self.pos} unexpected bytes after the last record",
                             "the file is corrupt; re-copy it or re-export the COLMAP model")


def _check_binary(model: Path) -> None:
    """Validate cameras.bin / images.bin / points3D.bin layouts (COLMAP's model/reconstruction_io)."""
    models = _model_num_params()
    r = _Reader(model / "cameras.bin")
    camera_ids = set()
    for _ in range(r.count(24, "cameras")):
        cid, mid, w, h = r.take("<iiQQ", "a camera record")
        if mid not in models:
            raise InputError(r.path, f"camera {cid} has unknown camera model id {mid} (byte {r.pos - 24} "
                             "of the file)", "the file is corrupt or not a COLMAP cameras.bin; re-copy it or "
                             f"re-export the model with one of {', '.join(SUPPORTED_MODELS)}")
        name, nparams = models[mid]
        if name not in SUPPORTED_MODELS:
            raise _unsupported(r.path, name, f"camera {cid}")
        params = r.take(f"<{nparams}d", "camera parameters")
        if not (0 < w < 1 << 20 and 0 < h < 1 << 20) or not np.all(np.isfinite(params)):
            raise InputError(r.path, f"camera {cid} has an invalid size {w}x{h} or non-finite parameters",
                             "re-export the COLMAP model")
        camera_ids.add(cid)
    r.done()

    r = _Reader(model / "images.bin")
    for _ in range(r.count(64 + 4 + 1 + 8, "images")):
        iid, *_pose, cid = r.take("<i7di", "an image record")
        end = r.buf.find(b"\0", r.pos)
        if end < 0:
            raise r.truncated("file ends inside an image name")
        try:
            name = r.buf[r.pos:end].decode("utf-8")
        except UnicodeDecodeError:  # pycolmap would raise it when the name is read
            raise InputError(r.path, f"image {iid} has a name that is not UTF-8 text (byte {r.pos} of the file)",
                             "the file is corrupt; re-copy it or re-export the COLMAP model") from None
        r.pos = end + 1
        if cid not in camera_ids:
            raise InputError(r.path, f"image {name!r} refers to camera {cid}, which cameras.bin does not have",
                             "the model files do not belong together; re-export the COLMAP model")
        (npts,) = r.take("<Q", f"the keypoint count of image {name!r}")
        r.skip(24 * npts, f"the keypoints of image {name!r}")
    r.done()

    r = _Reader(model / "points3D.bin")
    for _ in range(r.count(8 + 24 + 3 + 8 + 8, "points")):
        r.take("<Q3d3Bd", "a point record")
        (ntrack,) = r.take("<Q", "a track length")
        r.skip(8 * ntrack, "a point track")
    r.done()


def _check_text(model: Path) -> None:
    """Validate cameras.txt / images.txt / points3D.txt token counts."""
    models = {name: n for name, n in _model_num_params().values()}

    def lines(path: Path):
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise InputError(path, "is not a text file", "re-export the COLMAP model as text") from None
        return text.splitlines()

    def bad(path: Path, lineno: int, what: str) -> InputError:
        return InputError(path, f"line {lineno}: {what}", "the file is corrupt; re-export the COLMAP model")

    path = model / "cameras.txt"
    for i, line in enumerate(lines(path), 1):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        if len(tok) < 4:
            raise bad(path, i, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        if tok[1] not in models:
            raise bad(path, i, f"unknown camera model {tok[1]!r}")
        if tok[1] not in SUPPORTED_MODELS:
            raise _unsupported(path, tok[1], f"line {i}")
        if len(tok) != 4 + models[tok[1]]:
            raise bad(path, i, f"{tok[1]} needs {models[tok[1]]} parameters, found {len(tok) - 4}")
        try:
            values = [float(t) for t in tok[2:]]
        except ValueError:
            raise bad(path, i, "non-numeric value") from None
        if not all(math.isfinite(v) for v in values):
            raise bad(path, i, f"camera {tok[0]} has a non-finite size or parameter")

    path = model / "images.txt"
    all_lines = lines(path)
    i = 0
    while i < len(all_lines):
        tok = all_lines[i].split()
        i += 1
        if not tok or tok[0].startswith("#"):
            continue
        if len(tok) < 10:
            raise bad(path, i, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        try:
            [float(t) for t in tok[1:9]]
        except ValueError:
            raise bad(path, i, "non-numeric pose") from None
        if i >= len(all_lines):
            raise bad(path, i, "file ends before the POINTS2D line of this image")
        if len(all_lines[i].split()) % 3:
            raise bad(path, i + 1, "POINTS2D must be (X, Y, POINT3D_ID) triples")
        i += 1

    path = model / "points3D.txt"
    for i, line in enumerate(lines(path), 1):
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        if len(tok) < 8 or len(tok) % 2:
            raise bad(path, i, "expected POINT3D_ID X Y Z R G B ERROR TRACK[] (pairs)")
        try:
            [float(t) for t in tok[1:8]]
        except ValueError:
            raise bad(path, i, "non-numeric value") from None


def _read_reconstruction(model: Path) -> pycolmap.Reconstruction:
    binary = all((model / f"{f}.bin").is_file() for f in _MODEL_FILES)
    text = all((model / f"{f}.txt").is_file() for f in _MODEL_FILES)
    if not (binary or text):
        ext = ".bin" if (model / "cameras.bin").is_file() else ".txt"
        missing = [f + ext for f in _MODEL_FILES if not (model / f"{f}{ext}").is_file()]
        raise InputError(model / missing[0], "COLMAP model file is missing",
                         f"a model needs {', '.join(f + ext for f in _MODEL_FILES)}; re-export it")
    (_check_binary if binary else _check_text)(model)
    try:
        return pycolmap.Reconstruction(str(model))
    except Exception as e:  # pycolmap's messages do not name the file; attribute them as best we can
        msg = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
        ext = ".bin" if binary else ".txt"
        culprit = {"Camera": "cameras", "Rig": "images", "Image": "points3D"}.get(msg.split(" ")[0], None)
        if "VerifyParams" in msg:  # a camera whose parameters do not fit its model
            culprit = "cameras"
        path = model / f"{culprit}{ext}" if culprit else model
        raise InputError(path, f"COLMAP model cannot be read: {msg}",
                         "the file is corrupt or the model files do not belong together; re-export it") from None


# ----------------------------------------------------------------------------------------------


def _intrinsics(cam: pycolmap.Camera, model_file: Path) -> Intrinsics:
    name = cam.model.name
    p = [float(v) for v in cam.params]
    w, h = int(cam.width), int(cam.height)
    if name == "SIMPLE_PINHOLE":
        return Intrinsics(w, h, p[0], p[0], p[1], p[2])
    if name == "PINHOLE":
        return Intrinsics(w, h, p[0], p[1], p[2], p[3])
    if name == "SIMPLE_RADIAL":
        return Intrinsics(w, h, p[0], p[0], p[1], p[2], (p[3], 0.0, 0.0, 0.0))
    if name == "RADIAL":
        return Intrinsics(w, h, p[0], p[0], p[1], p[2], (p[3], p[4], 0.0, 0.0))
    if name == "OPENCV":
        return Intrinsics(w, h, p[0], p[1], p[2], p[3], tuple(p[4:8]))
    if name == "FULL_OPENCV":  # k1 k2 p1 p2 k3 k4 k5 k6: OpenCV's rational model, same order
        return Intrinsics(w, h, p[0], p[1], p[2], p[3], tuple(p[4:12]))
    # theta_d = theta (1 + k1 theta^2 + ...): COLMAP's models.h and cv2.fisheye agree
    if name == "SIMPLE_FISHEYE":
        return fisheye_intrinsics(w, h, p[0], p[0], p[1], p[2])
    if name == "FISHEYE":
        return fisheye_intrinsics(w, h, p[0], p[1], p[2], p[3])
    if name == "SIMPLE_RADIAL_FISHEYE":
        return fisheye_intrinsics(w, h, p[0], p[0], p[1], p[2], (p[3],))
    if name == "RADIAL_FISHEYE":
        return fisheye_intrinsics(w, h, p[0], p[0], p[1], p[2], (p[3], p[4]))
    if name == "OPENCV_FISHEYE":
        return fisheye_intrinsics(w, h, p[0], p[1], p[2], p[3], tuple(p[4:8]))
    raise _unsupported(model_file, name, f"camera {cam.camera_id}")


def _cam_from_world(image: pycolmap.Image) -> np.ndarray:
    T = image.cam_from_world
    T = T() if callable(T) else T  # a method in pycolmap >= 3.12, a property before
    M = np.eye(4)
    M[:3, :4] = np.asarray(T.matrix(), dtype=np.float64)
    return M


def load_colmap(root: str | Path, downscale: float = 1.0, test_every: int = 8,
                load_images: bool = True, background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Scene:
    """Load a COLMAP scene as undistorted pinhole cameras.

    Args:
        root: scene folder with ``sparse/0`` (or ``sparse``) holding a binary or text model and
            ``images/`` (Mip-NeRF 360, Tanks & Temples and Deep Blending as 3DGS ships them).
        downscale: resize images by 1 / downscale (cv2.INTER_AREA) and scale the intrinsics; a
            whole number N reads ``images_N/`` instead where it exists (:mod:`splatk.data.downscaled`).
        test_every: image i (in name order) is a test view when i % test_every == 0; 0 = no test views.
        load_images: decode the images (else only headers are read, to check sizes).
        background: RGB in [0, 1] that RGBA images are composited on.

    Returns:
        Scene with ``points: [P, 3]`` and ``point_colors: [P, 3]`` in [0, 1] from points3D.

    Raises:
        InputError: naming the file, for any missing, truncated or inconsistent input.
    """
    root = Path(root)
    downscale = check_downscale(downscale)
    if not root.is_dir():
        raise InputError(root, "scene folder does not exist", "check the path")
    model = find_model_dir(root)
    if model is None:
        raise InputError(root, "no COLMAP model found (looked for sparse/0/cameras.bin and sparse/cameras.bin)",
                         "run COLMAP/pycolmap SfM or pass a folder with sparse/0")
    image_dir = root / "images"
    if not image_dir.is_dir():
        raise InputError(image_dir, "image folder does not exist", "put the images the model names in root/images")

    rec = _read_reconstruction(model)
    ext = ".bin" if (model / "cameras.bin").is_file() and (model / "images.bin").is_file() else ".txt"
    cam_file, img_file, pts_file = (model / f"{f}{ext}" for f in _MODEL_FILES)

    und = Undistorter()
    intrinsics = {cid: _intrinsics(cam, cam_file) for cid, cam in rec.cameras.items()}
    for cid, intr in sorted(intrinsics.items()):
        pinhole(intr, und, cam_file, f"camera {cid}")
    images = sorted((im for im in rec.images.values() if getattr(im, "has_pose", True)), key=lambda im: im.name)
    if not images:
        raise InputError(img_file, "COLMAP model has no registered images", "re-run SfM")
    for a, b in zip(images, images[1:]):
        if a.name == b.name:
            raise InputError(img_file, f"images {a.image_id} and {b.image_id} have the same name {a.name!r}",
                             "remove the duplicate image from the model (or re-run SfM)")

    # 1. every input checked before any decoding
    views = []
    for im in images:
        path = image_dir / im.name
        if has_control_characters(im.name):
            raise InputError(img_file, f"image {im.image_id} has a name with control characters ({im.name!r})",
                             "rename the image (and its entry in the model) or re-run SfM")
        if not im.name or not is_inside(path, image_dir) or path == image_dir:
            raise InputError(img_file, f"image name {im.name!r} points outside the image folder {image_dir}",
                             "image names are paths relative to root/images; fix the model or re-run SfM")
        pose = _cam_from_world(im)
        w2c = rigid_or_none(pose)
        if w2c is None:
            what = "a non-finite" if not np.all(np.isfinite(pose)) else "an invalid (non-rigid)"
            raise InputError(img_file, f"image {im.name!r} has {what} pose",
                             "re-run SfM or remove the image from the model")
        check_translation(w2c, img_file, f"image {im.name!r}")
        views.append(View(im.name, intrinsics[im.camera_id], w2c, path))
    camera_of = {im.name: im.camera_id for im in images}
    small_views, remaining = use_downscaled(views, root, downscale)  # images_N/ (Mip-NeRF 360)
    if remaining == downscale:  # the originals: each is its camera's size
        for view in views:
            check_image_file(view.path, img_file.name)
            w, h = image_size(view.path)
            intr = view.intr
            if (w, h) != (intr.width, intr.height):
                raise InputError(view.path, f"image is {w}x{h} but its camera {camera_of[view.name]} in "
                                 f"{cam_file.name} is {intr.width}x{intr.height}",
                                 "use the images the model was made from (a resized copy goes in images_N/ "
                                 "for --downscale N), or rescale the model")
    else:
        for view in small_views:
            pinhole(view.intr, und, cam_file, f"camera {camera_of[view.name]} at {view.intr.width}x{view.intr.height}")
    views, downscale = small_views, remaining

    if rec.num_points3D():
        pts = sorted(rec.points3D.items())
        xyz = np.array([p.xyz for _, p in pts], dtype=np.float64)
        rgb = np.array([p.color for _, p in pts], dtype=np.float64) / 255.0
        bad = ~(np.abs(xyz) <= FLOAT32_SAFE).all(1)  # NaN compares False
        if bad.any():
            raise InputError(pts_file, f"{int(bad.sum())} points have non-finite or out-of-range positions "
                             f"(at most {FLOAT32_SAFE:g} in magnitude)", "re-run SfM or filter the point cloud")
    else:
        xyz, rgb = np.zeros((0, 3)), np.zeros((0, 3))

    # 2. decode, undistort, downscale
    warnings: list[str] = []
    cams = make_cameras(views, und, downscale, load_images, background, warnings)
    train, test = split_every(cams, test_every)
    return Scene(root=root, train=train, test=test,
                 points=torch.from_numpy(xyz.astype(np.float32)), point_colors=torch.from_numpy(rgb.astype(np.float32)),
                 background=tuple(float(b) for b in background), source="colmap", warnings=warnings)
