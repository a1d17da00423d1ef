"""Tiny copies of standard dataset layouts, built in tmp_path from the shared scenes or the demo
scene: nerfstudio (fisheye intrinsics, masks, a PLY point cloud), Mip-NeRF 360 (images_N/),
Tanks & Temples / Deep Blending as 3DGS ships them."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import plyfile

from splatk.data import load_scene
from splatk.data.types import Camera

#: OpenCV camera axes <-> OpenGL/Blender camera axes (its own inverse)
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
#: the fisheye copy's lens: cv2.fisheye k1..k4
FISHEYE_K = (0.08, 0.02, -0.01, 0.002)


def cv_K(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """OpenCV's K (integer pixel centres) of a half-pixel-convention camera."""
    return np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])


def fisheye_image(cam: Camera, width: int, height: int, f: float) -> np.ndarray:
    """``cam``'s pinhole image as an OpenCV fisheye lens (focal ``f``, :data:`FISHEYE_K`, centred)
    at the same pose sees it: each fisheye pixel's ray (cv2.fisheye.undistortPoints) is looked up
    in the pinhole image (inverse mapping)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays = cv2.fisheye.undistortPoints(np.stack([u, v], -1).reshape(-1, 1, 2), cv_K(f, f, width / 2, height / 2),
                                       np.array(FISHEYE_K).reshape(4, 1)).reshape(height, width, 2)
    mx = (rays[..., 0] * cam.fx + cam.cx - 0.5).astype(np.float32)
    my = (rays[..., 1] * cam.fy + cam.cy - 0.5).astype(np.float32)
    return cv2.remap(cam.image.numpy(), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """A binary PLY as nerfstudio writes it: float x, y, z and uchar red, green, blue."""
    v = np.empty(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"),
                                  ("blue", "u1")])
    for i, c in enumerate("xyz"):
        v[c] = xyz[:, i]
    for i, c in enumerate(("red", "green", "blue")):
        v[c] = np.clip(rgb[:, i] * 255 + 0.5, 0, 255).astype(np.uint8)
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")]).write(str(path))


def nerfstudio_copy(source: Path, root: Path, views: int = 4, downscale: float = 2.0, fisheye: bool = True,
                    masks: bool = True, points: int = 300, extra: dict | None = None) -> Path:
    """A nerfstudio dataset made from the COLMAP scene ``source``: ``transforms.json`` with
    ``camera_model: OPENCV_FISHEYE`` (images warped to that lens, 4/5 of the pinhole size,
    focal 0.65 x the pinhole's), ``images/``, ``masks/`` (the left quarter masked out) and
    ``sparse_pc.ply`` (the first ``points`` SfM points); ``extra``: more top-level fields."""
    src = load_scene(source, downscale=downscale, test_every=0)
    cams = src.train[:views]
    first = cams[0]
    width, height = (int(first.width * 0.8), int(first.height * 0.8)) if fisheye else (first.width, first.height)
    f = 0.65 * first.fx if fisheye else first.fx
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    frames = []
    for cam in cams:
        name = Path(cam.name).stem + ".png"
        img = fisheye_image(cam, width, height, f) if fisheye else cam.image.numpy()
        cv2.imwrite(str(root / "images" / name), np.ascontiguousarray(img[..., ::-1]))
        frame = {"file_path": f"images/{name}",
                 "transform_matrix": (np.linalg.inv(cam.world_to_cam.double().numpy()) @ GL_TO_CV).tolist()}
        if masks:
            mask = np.full((height, width), 255, np.uint8)
            mask[:, : width // 4] = 0
            cv2.imwrite(str(root / "masks" / name), mask)
            frame["mask_path"] = f"masks/{name}"
        frames.append(frame)
    doc = {"camera_model": "OPENCV_FISHEYE" if fisheye else "OPENCV", "fl_x": f, "fl_y": f,
           "cx": width / 2, "cy": height / 2, "w": width, "h": height, "frames": frames}
    if fisheye:
        doc.update(dict(zip(("k1", "k2", "k3", "k4"), FISHEYE_K)))
    if points:
        write_ply(root / "sparse_pc.ply", src.points[:points].double().numpy(), src.point_colors[:points].double().numpy())
        doc["ply_file_path"] = "sparse_pc.ply"
    doc.update(extra or {})
    (root / "transforms.json").write_text(json.dumps(doc))
    return root


def colmap_copy(source: Path, root: Path, images: int | None = None) -> Path:
    """``root/sparse/0`` (the model, copied) and ``root/images`` (links to the images) of the
    COLMAP scene ``source``; with ``images``, only the first that many image files are linked."""
    (root / "sparse").mkdir(parents=True)
    shutil.copytree(source / "sparse" / "0", root / "sparse" / "0")
    (root / "images").mkdir()
    for i, img in enumerate(sorted((source / "images").iterdir())):
        if images is None or i < images:
            (root / "images" / img.name).symlink_to(img)
    return root


def write_downscaled(folder: Path, factor: int, size: tuple[int, int] | None = None) -> Path:
    """``folder_N`` beside ``folder``: each image at 1/``factor`` (sizes rounded up, as the
    Mip-NeRF 360 release has them) or at ``size``."""
    out = folder.with_name(f"{folder.name}_{factor}")
    out.mkdir()
    for img in sorted(folder.iterdir()):
        pixels = cv2.imread(str(img), cv2.IMREAD_UNCHANGED)
        h, w = pixels.shape[:2]
        new = size or (-(-w // factor), -(-h // factor))
        cv2.imwrite(str(out / img.name), cv2.resize(pixels, new, interpolation=cv2.INTER_AREA))
    return out
