"""A small built-in scene: analytically ray-cast spheres in NeRF-synthetic layout (no downloads).

``make_demo_scene`` writes ``transforms_train.json`` / ``transforms_test.json`` and RGBA PNGs
(``train/r_<i>.png``, ``test/r_<i>.png``, listed without extension as NeRF-synthetic does).
The background is transparent, so :func:`splatk.data.load_scene` composites it on white.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np

#: OpenCV camera axes (x right, y down, z forward) -> OpenGL/Blender (x right, y up, z back)
_CV_TO_GL = np.diag([1.0, -1.0, -1.0])
CAMERA_ANGLE_X = 0.6911112070083618  # the NeRF-synthetic lego field of view (about 39.6 degrees)
_SUPERSAMPLE = 2  # rays per pixel side, for anti-aliased edges and alpha


def _spheres(rng: np.random.Generator) -> list[tuple[np.ndarray, float, np.ndarray, bool]]:
    """(centre [3], radius, rgb [3] in [0, 1], checkered) of the demo objects, world z up."""
    out = [(np.array([0.0, 0.0, 0.0]), 0.55, np.array([0.95, 0.85, 0.2]), True)]
    palette = np.array([[0.85, 0.15, 0.15], [0.15, 0.45, 0.9], [0.2, 0.75, 0.3], [0.75, 0.3, 0.85]])
    base = rng.uniform(0.0, 2.0 * math.pi)
    for k, rgb in enumerate(palette):
        a = base + k * math.pi / 2 + rng.uniform(-0.3, 0.3)
        r = rng.uniform(0.85, 1.0)
        centre = np.array([r * math.cos(a), r * math.sin(a), rng.uniform(-0.35, 0.35)])
        out.append((centre, float(rng.uniform(0.22, 0.3)), rgb, False))
    return out


def _look_at_c2w(eye: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """[4, 4] camera-to-world, OpenGL camera axes, camera at ``eye`` looking at the origin."""
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, fwd)
    M = np.eye(4)
    M[:3, :3] = np.stack([right, cam_up, -fwd], axis=1)
    M[:3, 3] = eye
    return M


def _render(c2w_gl: np.ndarray, size: int, focal: float, spheres, light: np.ndarray) -> np.ndarray:
    """[size, size, 4] uint8 RGBA by ray casting (pixel centres at i + 0.5, supersampled)."""
    s = _SUPERSAMPLE
    t = (np.arange(size * s) + 0.5) / s  # sub-pixel sample positions in pixel units
    u, v = np.meshgrid(t, t, indexing="xy")
    dirs_cv = np.stack([(u - size / 2) / focal, (v - size / 2) / focal, np.ones_like(u)], axis=-1)
    R = c2w_gl[:3, :3] @ _CV_TO_GL  # camera (OpenCV axes) -> world
    d = dirs_cv.reshape(-1, 3) @ R.T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = c2w_gl[:3, 3]
    n_rays = d.shape[0]
    depth = np.full(n_rays, np.inf)
    rgb = np.zeros((n_rays, 3))
    for centre, radius, colour, checker in spheres:
        oc = o - centre
        b = d @ oc
        disc = b * b - (oc @ oc - radius * radius)
        hit = disc > 0
        tt = np.where(hit, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        closer = hit & (tt > 0) & (tt < depth)
        if not closer.any():
            continue
        depth[closer] = tt[closer]
        p = o + tt[closer, None] * d[closer]
        n = (p - centre) / radius
        col = np.broadcast_to(colour, n.shape).copy()
        if checker:  # 8 x 12 checkerboard in latitude / longitude
            lat = np.arccos(np.clip(n[:, 2], -1, 1))
            lon = np.arctan2(n[:, 1], n[:, 0]) + math.pi
            odd = (np.floor(lat / math.pi * 8) + np.floor(lon / (2 * math.pi) * 12)) % 2 == 1
            col[odd] = col[odd] * 0.25 + np.array([0.05, 0.1, 0.35])
        shade = 0.3 + 0.7 * np.clip(n @ light, 0.0, 1.0)
        rgb[closer] = col * shade[:, None]
    alpha = np.isfinite(depth).astype(np.float64)
    img = np.concatenate([rgb, alpha[:, None]], axis=1).reshape(size, s, size, s, 4).mean(axis=(1, 3))
    # straight (not premultiplied) alpha, as PNG stores it
    a = img[..., 3:4]
    img[..., :3] = np.where(a > 0, img[..., :3] / np.maximum(a, 1e-8), 0.0)
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


def make_demo_scene(out_dir: str | Path, num_views: int = 24, size: int = 96, seed: int = 0) -> Path:
    """Write the demo scene and return its folder.

    Five spheres (a checkered one at the origin and four coloured ones around it) seen by
    ``num_views`` cameras on a hemisphere of radius 4 looking at the origin, at three
    elevations. Every 8th view is a test view (``transforms_test.json``), the rest train.

    Args:
        out_dir: folder to write (created; existing demo files are replaced).
        num_views: number of cameras (>= 2).
        size: square image size in pixels.
        seed: places and sizes the small spheres; the same seed gives byte-identical files.
    """
    if num_views < 2 or size < 8:
        raise ValueError("make_demo_scene needs num_views >= 2 and size >= 8")
    out = Path(out_dir)
    rng = np.random.default_rng(seed)
    spheres = _spheres(rng)
    light = np.array([0.5, 0.3, 0.8])
    light /= np.linalg.norm(light)
    focal = 0.5 * size / math.tan(0.5 * CAMERA_ANGLE_X)
    elevations = np.radians([12.0, 30.0, 50.0])
    frames: dict[str, list[dict]] = {"train": [], "test": []}
    for i in range(num_views):
        az = 2.0 * math.pi * i / num_views
        el = elevations[i % len(elevations)]
        eye = 4.0 * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        c2w = _look_at_c2w(eye)
        split = "test" if i % 8 == 0 else "train"
        (out / split).mkdir(parents=True, exist_ok=True)
        rgba = _render(c2w, size, focal, spheres, light)
        if not cv2.imwrite(str(out / split / f"r_{i}.png"), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA)):
            raise OSError(f"could not write {out / split / f'r_{i}.png'}")
        frames[split].append({"file_path": f"./{split}/r_{i}",
                              "transform_matrix": [[round(float(x), 10) for x in row] for row in c2w]})
    for split, fr in frames.items():
        data = {"camera_angle_x": CAMERA_ANGLE_X, "frames": fr}
        (out / f"transforms_{split}.json").write_text(json.dumps(data, indent=2) + "\n")
    return out
