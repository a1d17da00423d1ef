"""instant-ngp / nerfstudio / NeRF-synthetic scenes: ``transforms.json`` or ``transforms_{train,test}.json``.

``transform_matrix`` is camera-to-world with OpenGL/Blender camera axes (x right, y up, z back);
it becomes an OpenCV world-to-camera by flipping the camera's y and z axes and inverting.
Intrinsics are global (``fl_x, fl_y, cx, cy, w, h`` or ``camera_angle_x`` [+ ``camera_angle_y``])
and may be overridden per frame; ``k1, k2, p1, p2`` [+ ``k3``] distortion is undistorted away,
and so is ``camera_model: OPENCV_FISHEYE`` with ``k1 .. k4`` (OpenCV's fisheye model).

nerfstudio's other fields: ``mask_path`` per frame (white: the pixel counts; masked pixels leave
the loss and the metrics), ``ply_file_path`` (the SfM points, used as the initial primitives).
A field splatk does not read is named in one warning per file (:attr:`Scene.warnings`), except
those in :data:`IGNORED_FIELDS`, which change nothing splatk reads.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ._common import (View, check_downscale, check_image_file, check_translation, has_control_characters, image_size,
                      is_inside, make_cameras, resolve_image, rigid_or_none, split_every)
from .cameras import Intrinsics, Undistorter, fisheye_intrinsics, pinhole
from .downscaled import use_downscaled
from .ply import read_ply_points
from .types import Scene

#: OpenGL/Blender camera axes -> OpenCV camera axes (flip y and z)
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])

_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y",
                   "k1", "k2", "k3", "k4", "p1", "p2", "is_fisheye", "camera_model")
#: nerfstudio's ``camera_model`` values read as OpenCV's perspective model (k1 k2 p1 p2 k3, and k4
#: as its rational term, as nerfstudio hands them to cv2)
PERSPECTIVE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
FISHEYE_MODELS = ("OPENCV_FISHEYE",)
#: fields read besides the intrinsics
_USED_TOP = {"frames", "ply_file_path", *_INTRINSIC_KEYS}
_USED_FRAME = {"file_path", "transform_matrix", "mask_path", *_INTRINSIC_KEYS}
#: fields accepted without a warning: they steer other tools (a NeRF's bounding box and scene
#: normalisation, a frame's sharpness or Blender rotation, field-of-view copies in degrees,
#: the transform nerfstudio already applied to poses and points alike) and change nothing
#: splatk reads
IGNORED_FIELDS = frozenset({"aabb_scale", "scale", "offset", "sharpness", "rotation", "fovx", "fovy",
                            "applied_transform", "orientation_override", "auto_scale_poses_override",
                            "colmap_im_id"})


def find_transforms(root: Path) -> list[Path]:
    """The transforms JSON files of a scene folder (empty if it has none)."""
    if (root / "transforms_train.json").is_file():
        out = [root / "transforms_train.json"]
        if (root / "transforms_test.json").is_file():
            out.append(root / "transforms_test.json")
        return out
    if (root / "transforms.json").is_file():
        return [root / "transforms.json"]
    return []


def _read_json(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputError(path, "is not a UTF-8 text file", "regenerate the transforms file") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(path, f"is not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})",
                         "fix the syntax or regenerate the file") from None
    except ValueError as e:  # an integer longer than Python converts (4300 digits)
        raise InputError(path, f"is not valid JSON ({e})", "fix the value or regenerate the file") from None
    except RecursionError:
        raise InputError(path, "is not valid JSON (nested too deeply)", "regenerate the file") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise InputError(path, "has no 'frames' list", "a transforms file needs {\"frames\": [...]} with "
                         "file_path and transform_matrix per frame")
    return data


def _number(meta: dict, key: str, json_path: Path, frame: str) -> float | None:
    if key not in meta or meta[key] is None:
        return None
    try:
        v = float(meta[key])
    except (TypeError, ValueError, OverflowError):
        v = float("nan")
    if not math.isfinite(v):
        raise InputError(json_path, f"frame {frame!r}: {key} = {meta[key]!r} is not a finite number",
                         "fix the value in the file")
    return v


def _intrinsics(meta: dict, json_path: Path, frame: str, image_path: Path) -> Intrinsics:
    """Intrinsics from merged (global + per-frame) keys; the image header gives a missing size
    and must match a given one."""
    num = {k: _number(meta, k, json_path, frame) for k in _INTRINSIC_KEYS if k not in ("is_fisheye", "camera_model")}
    model = meta.get("camera_model", "OPENCV")
    if not isinstance(model, str) or model not in PERSPECTIVE_MODELS + FISHEYE_MODELS:
        raise InputError(json_path, f"frame {frame!r}: camera_model {model!r} is not supported",
                         f"supported: {', '.join(PERSPECTIVE_MODELS + FISHEYE_MODELS)}; undistort the images to a "
                         "pinhole camera first")
    fisheye = model in FISHEYE_MODELS
    if meta.get("is_fisheye") and not fisheye:
        raise InputError(json_path, "fisheye cameras (is_fisheye) without camera_model OPENCV_FISHEYE are not "
                         "supported", "undistort the images to a pinhole camera first, or give camera_model "
                         "OPENCV_FISHEYE with k1..k4 if the lens follows OpenCV's fisheye model")
    for key in ("camera_angle_x", "camera_angle_y"):
        if num[key] is not None and not 0.0 < num[key] < math.pi:
            raise InputError(json_path, f"frame {frame!r}: {key} = {num[key]:g} is not a field of view "
                             "between 0 and pi radians", f"{key} is the full field of view in radians "
                             "(e.g. 0.6911 for 39.6 degrees)")
    w, h = image_size(image_path)
    if num["w"] is not None and num["h"] is not None and (round(num["w"]), round(num["h"])) != (w, h):
        raise InputError(image_path, f"image is {w}x{h} but {json_path.name} says "
                         f"{round(num['w'])}x{round(num['h'])} (w, h) for frame {frame!r}",
                         "use the images the transforms file was made for, or fix w and h")
    fx, fy = num["fl_x"], num["fl_y"]
    if fx is None and num["camera_angle_x"] is not None:
        fx = 0.5 * w / math.tan(0.5 * num["camera_angle_x"])
    if fy is None and num["camera_angle_y"] is not None and num["fl_x"] is None:
        fy = 0.5 * h / math.tan(0.5 * num["camera_angle_y"])
    if fx is None and fy is not None:
        fx = fy
    if fy is None:
        fy = fx
    if fx is None:
        raise InputError(json_path, f"frame {frame!r} has no focal length",
                         "add fl_x (and fl_y) or camera_angle_x, globally or per frame")
    cx = num["cx"] if num["cx"] is not None else w / 2.0
    cy = num["cy"] if num["cy"] is not None else h / 2.0
    if fisheye:
        if num["p1"] or num["p2"]:
            raise InputError(json_path, f"frame {frame!r}: camera_model OPENCV_FISHEYE has no tangential "
                             f"distortion, but p1, p2 = {num['p1'] or 0:g}, {num['p2'] or 0:g}",
                             "remove p1 and p2, or use camera_model OPENCV")
        return fisheye_intrinsics(w, h, fx, fy, cx, cy, tuple(num[key] or 0.0 for key in ("k1", "k2", "k3", "k4")))
    k = [num[key] or 0.0 for key in ("k1", "k2", "p1", "p2", "k3")]
    if num["k4"]:  # OpenCV's rational model (k1 k2 p1 p2 k3 k4 k5 k6)
        k += [num["k4"], 0.0, 0.0]
    dist = tuple(k) if any(k) else ()
    return Intrinsics(w, h, fx, fy, cx, cy, dist)


def _scene_file(json_path: Path, value, key: str, where: str) -> Path:
    """The path a field (``mask_path``, ``ply_file_path``) names, relative to the transforms
    file's folder, checked to be a name inside that folder."""
    base = json_path.parent
    if not isinstance(value, str) or not value or has_control_characters(value):
        raise InputError(json_path, f"{where}: {key} {value!r} is not a file name",
                         f"{key} is a path relative to the transforms file")
    path = base / value
    if not is_inside(path, base):
        raise InputError(json_path, f"{where}: {key} {value!r} points outside the scene folder {base}",
                         "keep the files inside the scene folder (a symbolic link inside it is fine)")
    return path


def _mask(json_path: Path, fr: dict, i: int, image: Path, size: tuple[int, int]) -> Path | None:
    """The frame's mask file (checked: present, decodable header, the image's size), or None."""
    if fr.get("mask_path") is None:
        return None
    path = resolve_image(_scene_file(json_path, fr["mask_path"], "mask_path", f"frame {i}"))
    if path is None:
        raise InputError(json_path.parent / str(fr["mask_path"]), f"mask of frame {i} in {json_path.name} does "
                         "not exist", f"add the mask or remove mask_path from the frame in {json_path.name}")
    check_image_file(path, json_path.name)
    if image_size(path) != size:
        w, h = image_size(path)
        raise InputError(path, f"mask is {w}x{h} but its image {image.name} is {size[0]}x{size[1]}",
                         "make the mask at the size of the full-size image")
    return path


def _frames(json_path: Path, data: dict, und: Undistorter, unused: set[str]) -> list[View]:
    """Check every frame of one file: image (and mask) inside the scene folder, present, listed
    once and non-empty; pose finite and rigid; intrinsics complete and valid. Adds the names of
    fields splatk does not read to ``unused``."""
    base = json_path.parent
    glob = {k: data[k] for k in _INTRINSIC_KEYS if k in data}
    unused.update(k for k in data if k not in _USED_TOP and k not in IGNORED_FIELDS)
    out = []
    first_use: dict[Path, int] = {}
    for i, fr in enumerate(data["frames"]):
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise InputError(json_path, f"frame {i} lacks file_path or transform_matrix", "fix the frame entry")
        unused.update(f"frames[].{k}" for k in fr if k not in _USED_FRAME and k not in IGNORED_FIELDS)
        rel = fr["file_path"]
        if not isinstance(rel, str) or not rel or has_control_characters(rel):
            raise InputError(json_path, f"frame {i}: file_path {rel!r} is not a file name",
                             "file_path is the image path relative to the transforms file")
        listed = base / rel
        if not is_inside(listed, base):
            raise InputError(json_path, f"frame {i}: file_path {rel!r} points outside the scene folder {base}",
                             "keep the images inside the scene folder (a symbolic link inside it is fine)")
        path = resolve_image(listed)
        if path is None:
            raise InputError(listed, f"image of frame {i} in {json_path.name} does not exist",
                             f"add the image or remove the frame from {json_path.name}")
        check_image_file(path, json_path.name)
        key = Path(os.path.normpath(os.path.abspath(path)))
        if key in first_use:
            raise InputError(json_path, f"frames {first_use[key]} and {i} both use image {rel!r}",
                             "remove the duplicate frame")
        first_use[key] = i
        try:
            c2w = np.array(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError, OverflowError, RecursionError):
            c2w = np.full((4, 4), np.nan)
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            raise InputError(json_path, f"frame {rel!r}: transform_matrix is not a finite 4x4 matrix "
                             "(NaN, inf or a wrong shape)", "fix or remove the frame")
        c2w = rigid_or_none(c2w)
        if c2w is None:
            raise InputError(json_path, f"frame {rel!r}: transform_matrix is not a rigid transform "
                             "(its rotation part is not orthonormal with det +1)", "fix or remove the frame")
        w2c = np.linalg.inv(c2w @ GL_TO_CV)
        check_translation(w2c, json_path, f"frame {rel!r}")
        intr = _intrinsics({**glob, **{k: fr[k] for k in _INTRINSIC_KEYS if k in fr}}, json_path, rel, path)
        pinhole(intr, und, json_path, f"frame {rel!r}")
        mask = _mask(json_path, fr, i, path, (intr.width, intr.height))
        name = path.relative_to(base).as_posix() if path.is_relative_to(base) else path.as_posix()
        out.append(View(name, intr, w2c, path, mask))
    return out


def _points(files: list[Path], docs: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """The point cloud of the first file naming ``ply_file_path`` (else none)."""
    for json_path, data in zip(files, docs):
        if data.get("ply_file_path") is not None:
            return read_ply_points(_scene_file(json_path, data["ply_file_path"], "ply_file_path", "the file"))
    return np.zeros((0, 3)), np.zeros((0, 3))


def load_transforms(root: str | Path, downscale: float = 1.0, test_every: int = 8,
                    background: tuple[float, float, float] = (1.0, 1.0, 1.0), load_images: bool = True) -> Scene:
    """Load an instant-ngp, nerfstudio or NeRF-synthetic scene as undistorted pinhole cameras.

    Args:
        root: scene folder with ``transforms.json`` or ``transforms_train.json`` (+ ``transforms_test.json``),
            or the path of one transforms JSON file.
        downscale: resize images by 1 / downscale (cv2.INTER_AREA) and scale the intrinsics; a
            whole number N reads ``images_N/`` (for frames in ``images/``) instead where it exists
            (:mod:`splatk.data.downscaled`).
        test_every: used when there is no ``transforms_test.json``: frame i (in file name order) is a
            test view when i % test_every == 0; 0 = no test views.
        background: RGB in [0, 1] that RGBA images are composited on (NeRF-synthetic: white).
        load_images: decode the images (else only their headers are read, to check sizes).

    Returns:
        Scene with the points of ``ply_file_path`` (else ``points: [0, 3]``), masks from
        ``mask_path``, and a warning naming the fields splatk does not read.

    Raises:
        InputError: naming the file, for invalid JSON, missing/empty/corrupt images or masks, bad
            poses, incomplete intrinsics, an unsupported camera model or an unreadable PLY.
    """
    root = Path(root)
    downscale = check_downscale(downscale)
    if root.is_file() and root.suffix == ".json":
        files, root = [root], root.parent
    elif root.is_dir():
        files = find_transforms(root)
        if not files:
            raise InputError(root, "no transforms.json or transforms_train.json found",
                             "pass a folder with an instant-ngp or NeRF-synthetic transforms file")
    else:
        raise InputError(root, "scene folder does not exist", "check the path")
    background = tuple(float(b) for b in background)

    # 1. every input checked before any decoding
    und = Undistorter()
    docs = [_read_json(f) for f in files]
    warnings = []
    per_file = []
    for f, data in zip(files, docs):
        unused: set[str] = set()
        per_file.append(_frames(f, data, und, unused))
        if unused:
            warnings.append(f"{f}: splatk does not use {', '.join(sorted(unused))}; ignored")
    if len(per_file) == 2:  # the dataset's own train / test lists
        train_f, test_f = per_file
    else:
        train_f, test_f = split_every(sorted(per_file[0], key=lambda v: v.name), test_every)
    if not train_f and not test_f:
        raise InputError(files[0], "lists no frames", "add frames or pass another scene")
    views, remaining = use_downscaled(train_f + test_f, root, downscale)  # images_N/ (nerfstudio)
    if remaining != downscale:
        for view in views:
            pinhole(view.intr, und, view.path, f"the camera at {view.intr.width}x{view.intr.height}")
    xyz, rgb = _points(files, docs)

    # 2. decode, undistort, downscale
    cams = make_cameras(views, und, remaining, load_images, background, warnings)
    return Scene(root=root, train=cams[:len(train_f)], test=cams[len(train_f):], background=background,
                 points=torch.from_numpy(xyz.astype(np.float32)), point_colors=torch.from_numpy(rgb.astype(np.float32)),
                 source="transforms", warnings=warnings, test_listed=len(per_file) == 2)
