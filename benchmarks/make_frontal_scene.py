"""Make a forward-facing scene from the frontal part of a captured 360-degree COLMAP scene.

    python benchmarks/make_frontal_scene.py SRC_SCENE OUT_DIR [--fraction 0.33] [--start 0]

The reference direction is the mean viewing direction of ``fraction`` x N views that are
consecutive in name order from ``--start`` (phone-video captures are named along the arc); the
``fraction`` x N views whose viewing direction is closest to it are kept. OUT_DIR gets
``images`` (a symlink to SRC_SCENE/images, nothing is copied) and ``sparse/0`` as a COLMAP text
model holding only the kept images, their cameras and the SfM points that project into at least
one of them (tracks dropped). ``splatk fit OUT_DIR`` loads it like any COLMAP scene and applies
its own every-8th test split (name order) to the kept views. Write OUT_DIR outside the
repository: it points at the source scene's images by absolute path.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pycolmap


def _w2c(image) -> np.ndarray:
    T = image.cam_from_world
    T = T() if callable(T) else T  # a method in pycolmap >= 3.12, a property before
    return np.asarray(T.matrix(), dtype=np.float64)  # [3, 4]


def _quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion (w, x, y, z), COLMAP's order (Shepperd's method)."""
    t = np.trace(R)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = np.zeros(4)
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.asarray(q, dtype=np.float64)
    return q / np.linalg.norm(q)


def choose_views(directions: np.ndarray, fraction: float, start: int) -> np.ndarray:
    """Indices (into name order) of the round(fraction x N) views whose viewing direction is
    closest to the mean direction of as many consecutive views from ``start``."""
    n_all = len(directions)
    n = max(2, min(n_all, round(fraction * n_all)))
    arc = [(start + i) % n_all for i in range(n)]
    ref = directions[arc].mean(0)
    ref /= np.linalg.norm(ref)
    return np.sort(np.argsort(-(directions @ ref))[:n])


def visible_points(xyz: np.ndarray, cams: list[tuple[np.ndarray, object]]) -> np.ndarray:
    """Mask of the points in front of and inside the image of at least one (w2c, camera)."""
    seen = np.zeros(len(xyz), dtype=bool)
    for w2c, cam in cams:
        p = xyz @ w2c[:3, :3].T + w2c[:3, 3]
        z = p[:, 2]
        ok = z > 1e-6
        uv = np.asarray(cam.img_from_cam(p[ok]))  # pixel coordinates, distortion included
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        idx = np.nonzero(ok)[0][inside]
        seen[idx] = True
    return seen


def write_text_model(out: Path, rec, images: list, point_ids: list[int]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    cam_ids = sorted({im.camera_id for im in images})
    with open(out / "cameras.txt", "w") as f:
        for cid in cam_ids:
            cam = rec.cameras[cid]
            params = " ".join(repr(float(v)) for v in cam.params)
            f.write(f"{cid} {cam.model.name} {cam.width} {cam.height} {params}\n")
    with open(out / "images.txt", "w") as f:
        for im in images:
            w2c = _w2c(im)
            q = _quat_wxyz(w2c[:3, :3])
            t = w2c[:3, 3]
            f.write(f"{im.image_id} {' '.join(repr(float(v)) for v in q)} "
                    f"{' '.join(repr(float(v)) for v in t)} {im.camera_id} {im.name}\n\n")
    with open(out / "points3D.txt", "w") as f:
        for pid in point_ids:
            p = rec.points3D[pid]
            x, y, z = (repr(float(v)) for v in p.xyz)
            r, g, b = (int(v) for v in p.color)
            f.write(f"{pid} {x} {y} {z} {r} {g} {b} {float(p.error)!r}\n")


def make_frontal_scene(src: Path, out: Path, fraction: float = 0.33, start: int = 0) -> dict:
    model = src / "sparse" / "0"
    if not model.is_dir():
        model = src / "sparse"
    rec = pycolmap.Reconstruction(str(model))
    images = sorted(rec.images.values(), key=lambda im: im.name)
    w2cs = [_w2c(im) for im in images]
    directions = np.stack([w[2, :3] for w in w2cs])  # camera +z (viewing axis) in world coordinates
    keep = choose_views(directions, fraction, start)
    kept = [images[i] for i in keep]
    pids = sorted(rec.points3D.keys())
    xyz = np.array([rec.points3D[p].xyz for p in pids], dtype=np.float64).reshape(-1, 3)
    seen = visible_points(xyz, [(w2cs[i], rec.cameras[images[i].camera_id]) for i in keep])
    point_ids = [p for p, s in zip(pids, seen) if s]
    out.mkdir(parents=True, exist_ok=True)
    link = out / "images"
    if not link.exists():
        link.symlink_to((src / "images").resolve(), target_is_directory=True)
    write_text_model(out / "sparse" / "0", rec, kept, point_ids)
    info = {"source": str(src.resolve()), "fraction": fraction, "start": start,
            "views": [im.name for im in kept], "num_views": len(kept), "of_views": len(images),
            "points": len(point_ids), "of_points": len(pids),
            "spread_deg": float(np.degrees(np.arccos(np.clip(
                directions[keep] @ directions[keep].mean(0) / np.linalg.norm(directions[keep].mean(0)),
                -1, 1)).max()))}
    (out / "frontal.json").write_text(json.dumps(info, indent=2))
    return info


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path, help="a COLMAP scene folder (sparse/0 + images/)")
    ap.add_argument("out", type=Path, help="the new scene folder (outside the repository)")
    ap.add_argument("--fraction", type=float, default=0.33, help="share of the views kept")
    ap.add_argument("--start", type=int, default=0, help="first view (name order) of the reference arc")
    a = ap.parse_args()
    info = make_frontal_scene(a.src, a.out, a.fraction, a.start)
    print(json.dumps({k: v for k, v in info.items() if k != "views"}))


if __name__ == "__main__":
    main()
